"""Calibration files: every calibration format our users have (:mod:`.formats`, read and written,
to the one camera model of :mod:`gt3dkit.rig`) and the checks of a rig alone (:mod:`.show`).
Checks and refinement against the annotations are :mod:`gt3dkit.refine`."""
