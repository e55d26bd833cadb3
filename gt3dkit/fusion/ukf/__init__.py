"""The UKF, the primary estimator, in one place. Read it top to bottom:

* :mod:`.smoother`: :class:`~gt3dkit.fusion.ukf.smoother.UKFSmoother`, the estimator: the
  preparation it is given (:mod:`gt3dkit.fusion.preparation`), the noise search, the filter's
  two passes, the bones' messages and the run's result;
* :mod:`.config`: its settings, :class:`~gt3dkit.fusion.ukf.config.UKFConfig`;
* :mod:`.noise`: the process noise found from the data (the model's marginal likelihood);
* :mod:`.filtering`: the filter loop by the model's backend, and :mod:`.filterrun` what one run
  returns;
* :mod:`.measurement`: the stacked measurement model (what a row's state predicts in every
  camera), and :mod:`.rowsmodel` what the compiled filters read of it;
* :mod:`.boxupdate` (boxes: a compiled chain per object) and :mod:`.jointupdate` (keypoints: a
  compiled chain per person and joint): the measurement's statistical linear regression and the
  filter of each;
* :mod:`.sigma`: sigma points, the regression of a measurement block and the batched update's
  driver; :mod:`.update`: the iterated, robust information-form update of one row;
* :mod:`.filterloop`: the forward pass and the RTS pass, written once for both chains;
  :mod:`.kalman`: the linear steps (prediction, RTS, fading);
* :mod:`.bones`: a person's bone lengths tied to each joint's filter;
* :mod:`.initial` and :mod:`.blockcov`: the covariances held as their blocks.

The motion model (the state's layout, the transition and its noise) is
:mod:`gt3dkit.fusion.motion`, shared with the GTSAM smoother (:mod:`gt3dkit.fusion.graph`).
"""
