"""Calibration: the camera model and rig (:mod:`.model`), every calibration format our users
have (:mod:`.formats`), ``gt3d calib show`` checks (:mod:`.show`) and refinement of a rig from
the annotations (:mod:`.refine`, pycolmap bundle adjustment)."""
