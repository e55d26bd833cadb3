"""The second estimator: one GTSAM factor graph per object over all its frames
(:mod:`.smoother`), its per-object solutions (:mod:`.chain`) and its factors with their
Gauss-Newton (:mod:`.factors`). It shares the preparation (:mod:`gt3dkit.fusion.preparation`)
and the motion model (:mod:`gt3dkit.fusion.motion`) with the UKF, and for boxes alone the process
noise its likelihood search finds (:mod:`gt3dkit.fusion.ukf.noise`), nothing else.
"""
