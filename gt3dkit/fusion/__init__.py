"""Estimation: the estimators behind one interface (:mod:`.base`: the ``Estimator`` protocol, its
declared capabilities, and the registry by name), by role:

* :mod:`.preparation`: what every estimator starts from (rows, robust per-frame fits, occlusion,
  confidence, noise levels, identities);
* :mod:`.motion`: the state's layout and the motion model, shared;
* :mod:`.ukf`: the UKF, the primary estimator;
* :mod:`.graph`: the GTSAM smoother;
* :mod:`.triangulate`: the per-frame triangulation baseline.
"""
