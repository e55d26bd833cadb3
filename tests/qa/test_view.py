"""The QA's typed view of a prepared scene holds for what the estimators prepare (a renamed or
removed field of ``Prepared`` or ``Rows`` that QA reads fails here, not in a run)."""

from __future__ import annotations

import typing

import numpy as np

from gt3dkit.api import tiny_scenes
from gt3dkit.fusion.preparation.prepare import prepare
from gt3dkit.qa.view import PreparedView, RowsView


def test_prepared_scenes_are_the_view_qa_reads() -> None:
    for scene in tiny_scenes():
        pre = prepare(scene)
        assert isinstance(pre, PreparedView) and isinstance(pre.rows, RowsView)
        R = len(pre.rows.row_t)
        assert pre.rows.obs_row.shape[0] == R and pre.rows.box_z.shape[:1] == (R,)
        assert np.asarray(pre.sigma_box).shape == (4,) and isinstance(pre.box_tail, float)


def test_the_view_names_only_what_qa_reads() -> None:
    import inspect

    import gt3dkit.qa.anomalies as qa

    src = inspect.getsource(qa)
    for view in (PreparedView, RowsView):
        names = [n for n in dir(view) if not n.startswith("_") and isinstance(getattr(view, n), property)]
        assert names and all(n in src for n in names), names
    assert typing.get_type_hints(qa.find_anomalies)["pre"] is PreparedView
