"""Run by tests/test_project.py in the labels-check environment (make labels-env): datumaro,
CVAT's own import and export, reads a folder of CVAT for video 1.1 files (``cvat/<camera>.xml``)
and prints, as JSON, per camera (datumaro's subset) every shape it found that is not
``outside``: frame, track id (the ``track_id`` attribute), box and attributes."""

import json
import sys

import datumaro as dm

folder = sys.argv[1]
out: dict[str, list[dict[str, object]]] = {}
for item in dm.Dataset.import_from(folder, "cvat"):
    for ann in item.annotations:
        attrs = dict(ann.attributes)
        if attrs.get("outside"):
            continue
        x, y, w, h = ann.get_bbox()
        out.setdefault(item.subset, []).append({
            "frame": int(item.attributes.get("frame", -1)), "type": ann.type.name,
            "box": [x, y, x + w, y + h],
            "attributes": {k: v if isinstance(v, (str, int, float, bool)) else str(v)
                           for k, v in attrs.items()}})
print(json.dumps(out))
