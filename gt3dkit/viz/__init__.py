"""Pictures: open3d off-screen renders (:mod:`.render3d`, :mod:`.overview`) and the HTML
report (:mod:`.report`)."""
