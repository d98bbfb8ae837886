"""What a newcomer's audit of the README, the Python API, the page and
``/docs`` found (2026-12-06; docs/web_page.md, "Newcomer audit"): each
behavioural fix with the test that failed before it."""

from __future__ import annotations

import numpy as np


class _Cam:
    name, source = "cam", "measured"


def _sample(rgb, conf, threshold=None):
    s = {"status": "ok", "camera": _Cam, "profile": None, "warnings": [],
         "estimate": {"camera_rgb": list(rgb), "spectrum": [1.0, 1.0, 1.0], "wavelengths": [400, 550, 700],
                      "confidence": conf, "method": "learned"}}
    if threshold is not None:
        s["flag_threshold"] = threshold
    return s


def test_a_shared_light_is_flagged_as_its_images_are():
    """``wandell batch --lighting shared`` on the README's one CinemaDNG said
    "shared light: low confidence (0.49)" while the per-image run of the same
    file did not flag it: the learnt flag's threshold is 0.44, the shared
    light used 0.5. One image (or N identical ones) is now flagged as in
    per-image mode, and the items carry the shared light's flag."""
    from service.batch import items
    from service.batch.options import batch_options

    opts = batch_options(lighting="shared")
    rgb = [0.335, 0.827, 0.452]
    light = items.shared_light([_sample(rgb, 0.494, 0.4399)], opts)
    assert light["low_confidence"] is False and light["confidence"] == np.float64(0.494)
    assert items.shared_light([_sample(rgb, 0.42, 0.4399)], opts)["low_confidence"] is True
    # an estimate without the learnt flag: 0.5, as per image
    assert items.shared_light([_sample(rgb, 0.49)], opts)["low_confidence"] is True
    # each item gets the shared light's flag, not a second rule
    cam = type("C", (), {"name": "cam", "channels": 3, "wavelengths": np.array([400.0, 550, 700]),
                         "sensitivities": np.eye(3)})
    est = items._estimate_from_json(light, cam)
    assert items._estimate_json(est, cam)["low_confidence"] is False
