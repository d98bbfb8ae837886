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


def _warmth_left_minus_right(png: bytes) -> float:
    """log(red / blue) of the left third minus that of the right third."""
    import cv2

    im = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).astype(float)
    w = im.shape[1]
    f = lambda a: np.log(a[..., 2].mean() / a[..., 0].mean())    # noqa: E731 (BGR)
    return float(f(im[:, : w // 3]) - f(im[:, 2 * w // 3:]))


def test_the_preview_is_corrected_as_the_downloads_are():
    """A scene half under CIE A, half under D65. The page's picture is
    /v1/preview's; it refused ``spatial`` (422 unknown_field), so *Several
    lights: always one light* reached the words only, and it never applied
    the light map: with two lights found, the picture shown was corrected by
    one light while the downloads corrected each pixel by the map (measured:
    left-minus-right warmth 0.157 shown, 0.089 downloaded). Now it takes
    ``spatial`` and corrects as the downloads do (0.094 against 0.089 with
    the map, 0.157 against 0.153 without: the preview is of binned cells)."""
    from pathlib import Path
    import tempfile

    from fastapi.testclient import TestClient

    from service.app import app

    from .test_webpage import _two_light_dng

    with tempfile.TemporaryDirectory() as d:
        data = _two_light_dng(Path(d) / "two.dng").read_bytes()
    client = TestClient(app)
    files = {"file": ("two.dng", data)}
    warmth = {}
    for spatial in ("false", "true"):
        r = client.post("/v1/preview", files=files,
                        data={"wb": "corrected", "format": "png", "max_side": "256", "spatial": spatial})
        assert r.status_code == 200, r.text
        d = client.post("/v1/white-balance", files=files, data={"format": "png", "spatial": spatial})
        assert d.status_code == 200, d.text
        warmth[spatial] = _warmth_left_minus_right(r.content), _warmth_left_minus_right(d.content)
        assert abs(warmth[spatial][0] - warmth[spatial][1]) < 0.02, warmth
    assert abs(warmth["false"][0] - warmth["true"][0]) > 0.04, warmth      # the map is applied
    r = client.post("/v1/preview", files=files, data={"wb": "corrected", "spatial": "sometimes"})
    assert r.status_code == 422 and "spatial" in r.json()["detail"]


def test_the_page_explains_its_light_map_and_points_a_dng_to_the_dng_download():
    """Two things the page left to guesswork: the light map was a grid of
    pale colours with no key, and the XMP help told a DNG's owner to type
    Temperature/Tint by hand although the page offers the DNG with the white
    balance inside (what the README says to open in Lightroom)."""
    import re
    from pathlib import Path

    html = (Path(__file__).resolve().parents[1] / "service" / "static" / "index.html").read_text(encoding="utf-8")
    lights = html.split('id="lights"', 1)[1].split("</section>", 1)[0]
    key = re.sub(r"\s+", " ", lights.split('id="lights-key"', 1)[1])
    assert "coloured by its light" in key and "bluer" in key
    xmp = re.sub(r"\s+", " ", html.split("What the XMP sidecar does", 1)[1].split("</details>", 1)[0])
    assert "DNG with this white balance inside" in xmp and "IMG_0001.wandell.dng" in xmp
