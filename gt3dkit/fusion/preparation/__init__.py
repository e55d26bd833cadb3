"""What every estimator starts from, made once a run (:func:`~gt3dkit.fusion.preparation.prepare.prepare`
and its :class:`~gt3dkit.fusion.preparation.prepare.Prepared`): the object-frame rows
(:mod:`.rows`), the robust per-frame fits of the boxes (:mod:`.boxfit`, :mod:`.boxlm`) and the
keypoints, the edges nearer objects cut (:mod:`.occlusion`), what a detector's confidence says
(:mod:`.confidence`), the robust weights and noise levels (:mod:`.robust`); and before it, at
loading, the identities: the cross-camera association of per-camera ids (:mod:`.associate`) and of
detections without ids (:mod:`.detections`), and the splits of an id's impossible track
(:mod:`.identity`). Nothing here knows an estimator.
"""
