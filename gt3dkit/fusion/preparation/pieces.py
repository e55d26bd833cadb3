"""The preparation of a scene whose split ids' pieces were given ids of their own
(:func:`gt3dkit.api.split_ids`), taken from the whole scene's instead of made again: the pieces
hold the same object-frames with the same views, so their per-frame fits, kept edges and points,
noise levels and shape prior are the whole's (one preparation a run). Only the rows are laid out
anew, regrouped from the whole's (a piece's rows are its own span; the frames between two pieces
of an id, where no camera saw it, have no row), and what is made from each object's own frames
(the per-frame states of :meth:`Prepared.frame_state`) is made again from the pieces' rows.
"""

from __future__ import annotations

from dataclasses import fields, replace

import numpy as np

from gt3dkit.fusion.preparation.boxfit import BoxFit
from gt3dkit.fusion.preparation.prepare import Prepared
from gt3dkit.fusion.preparation.rows import regrouped
from gt3dkit.types import I64, Scene


def input_ids(obj_ids: I64, back: dict[int, tuple[int, int]]) -> I64:
    """``(O,)`` the input's id of each of the pieces' objects ``obj_ids`` (``back``: a piece's id ->
    the input's id and the piece; an id not in it is the input's own)."""
    return np.array([back.get(int(i), (int(i), 0))[0] for i in obj_ids], dtype=np.int64)


def pieces_prepared(pre: Prepared, pieces: Scene, back: dict[int, tuple[int, int]]) -> Prepared:
    """``pre``, the whole scene's preparation, for ``pieces`` (:func:`gt3dkit.api.split_ids`'s
    scene, ``back`` its map from a piece's id to the input's id and the piece): every per-row
    array taken at the pieces' rows (the rows' usable edges as the whole's preparation left them:
    the border's and the cut ones out), the rest as it is. The pieces' rows are the whole's,
    regrouped (:func:`gt3dkit.fusion.preparation.rows.regrouped`: what ``build_rows`` makes of the
    pieces, not built again): the pieces' observations are the whole's, in its order, their ids
    changed."""
    whole = pre.rows
    seen = (whole.obs_row >= 0).any(axis=1)
    view = whole.obs_row.max(axis=1)  # an annotated row's observation (the same in the pieces)
    if len(pieces.obs) <= int(view.max(initial=-1)):
        raise ValueError("pieces_prepared: the pieces' observations are not the whole scene's")
    new_id = np.where(seen, pieces.obs.track_id[np.maximum(view, 0)], -1)
    if not np.array_equal(input_ids(new_id[seen], back), whole.obj_ids[whole.row_o[seen]]):
        raise ValueError("pieces_prepared: the pieces are not a split of this scene's ids")
    rows, src = regrouped(whole, new_id)
    new_of = np.full(len(pre.rows), -1, np.int64)
    new_of[src] = np.arange(len(src))

    def take(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else a[src]

    fit = pre.fit
    if fit is not None:
        fit = BoxFit(**{f.name: getattr(fit, f.name)[src] for f in fields(BoxFit)})
    cut_by = None
    if pre.box_cut_by is not None:
        by = pre.box_cut_by[src]
        cut_by = np.where(by >= 0, new_of[np.maximum(by, 0)], -1)
    return replace(pre, rows=rows, fit=fit, box_keep=pre.box_keep[src], fit_reliable=pre.fit_reliable[src],
                   kpt0=take(pre.kpt0), kpt0_cov=take(pre.kpt0_cov), kpt_keep=pre.kpt_keep[src],
                   kpt_reliable=pre.kpt_reliable[src], kpt_var=pre.kpt_var[src], box_cut=take(pre.box_cut),
                   box_cut_by=cut_by, box_var_scale=take(pre.box_var_scale))
