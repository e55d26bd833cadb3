"""What one run of the UKF's filter returns (:func:`gt3dkit.fusion.ukf.filtering.run_filter`):
a typed result instead of a dictionary of arrays."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import NamedTuple

import numpy as np

from gt3dkit.fusion.ukf.blockcov import BlockCov
from gt3dkit.types import F64, JsonDict

#: The fields that hold arrays (per row or entry), not counters or descriptions.
ARRAYS = ("x", "P", "nis", "dof", "loglik_rows", "weights", "score2", "residual")


class RunScalars(NamedTuple):
    """A run's counters and descriptions (:meth:`FilterRun.scalars`)."""

    pd_repairs: int
    predictions_faded: int
    object_frames: int
    update_form: str
    update_passes_mean: float


@dataclass(frozen=True)
class FilterRun:
    """The rows' states ``x (R, n)`` and covariances ``P (R, n, n)`` (an array, or its blocks
    where the run was split: :class:`gt3dkit.fusion.ukf.blockcov.BlockCov`; smoothed when the run
    smoothed), per row the final update's normalised innovation square ``nis``, its degrees of
    freedom ``dof`` and log-likelihood ``loglik_rows`` ``(R,)`` (0 for rows not run), and, when
    the run collected them, per measurement entry the weights the final update used, each
    entry's point's squared leave-one-out score and the linearised residual ``(R, m)``.

    pd_repairs : covariances that needed an eigenvalue repair; predictions_faded : predictions
    the frame's own views contradicted (faded); object_frames : rows run; update_form : how the
    update ran; update_passes_mean : passes of the iterated update per row run
    """

    x: F64
    P: F64 | BlockCov
    nis: F64
    dof: F64
    loglik_rows: F64
    weights: F64 | None
    score2: F64 | None
    residual: F64 | None
    pd_repairs: int
    predictions_faded: int
    object_frames: int
    update_form: str
    update_passes_mean: float

    @property
    def mean_nis_per_dof(self) -> float:
        return float(self.nis.sum()) / max(float(self.dof.sum()), 1.0)

    @property
    def loglik(self) -> float:
        return float(self.loglik_rows.sum())

    def summary(self) -> JsonDict:
        """The run's scalars (for ``meta.json``)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)
               if f.name not in ARRAYS and getattr(self, f.name) is not None}
        return {**out, "mean_nis_per_dof": self.mean_nis_per_dof, "loglik": self.loglik}

    def scalars(self) -> RunScalars:
        """The counters and descriptions (no arrays): what :meth:`after` needs of a run."""
        return RunScalars(self.pd_repairs, self.predictions_faded, self.object_frames, self.update_form,
                          self.update_passes_mean)

    def after(self, earlier: RunScalars) -> FilterRun:
        """This run (of every row) as :meth:`merged` makes it from an earlier run whose
        :meth:`scalars` are ``earlier`` with ``on`` all rows, without that run's arrays (they
        can go before this run's are made): the earlier run's descriptions, the counters
        summed."""
        return replace(self, pd_repairs=earlier.pd_repairs + self.pd_repairs,
                       predictions_faded=earlier.predictions_faded + self.predictions_faded,
                       object_frames=earlier.object_frames, update_form=earlier.update_form,
                       update_passes_mean=earlier.update_passes_mean)

    def merged(self, new: FilterRun, on: np.ndarray) -> FilterRun:
        """This run with the rows ``on (R,)`` taken from ``new`` (a run of those rows' objects):
        states and covariances updated in place (they can be gigabytes), every per-row array
        and the counters combined."""
        self.x[on] = new.x[on]
        if new.P is not self.P:  # (a run written into this one's covariances: already there)
            self.P[on] = new.P[on]

        def take(a: F64 | None, b: F64 | None) -> F64 | None:
            if a is None or b is None:
                return None
            out = a.copy()
            out[on] = b[on]
            return out

        def kept(a: F64, b: F64) -> F64:
            out = a.copy()
            out[on] = b[on]
            return out

        return replace(self, nis=kept(self.nis, new.nis), dof=kept(self.dof, new.dof),
                       loglik_rows=kept(self.loglik_rows, new.loglik_rows),
                       weights=take(self.weights, new.weights), score2=take(self.score2, new.score2),
                       residual=take(self.residual, new.residual),
                       pd_repairs=self.pd_repairs + new.pd_repairs,
                       predictions_faded=self.predictions_faded + new.predictions_faded)
