"""Issue 13, item 2: pixels clipped in any channel render neutral, never a
colour cast (synthetic patches; the real file's glints are in
test_dng_render.py)."""

from __future__ import annotations

import numpy as np
import pytest

from recovery.dng_color import ColorProfile
from recovery.highlights import HIGHLIGHT_FULL, HIGHLIGHT_START, balance_highlights, highlight_shoulder

NEUTRAL = np.array([0.4533, 1.0, 0.53])     # a green-heavy camera neutral (the Blackmagic's as-shot)


def test_clipped_in_every_or_any_channel_becomes_neutral():
    px = np.array([[1.0, 1.0, 1.0],           # clipped everywhere: the gains would make it magenta
                   [1.0, 0.99, 1.0],          # the glint [65535, 64994, 65535]
                   [1.0, 0.6, 0.3],           # red clipped only
                   [0.2, 1.0, 0.3],           # green clipped only
                   [0.3, 0.5, 0.99]])         # blue clipped only
    w = balance_highlights(px, NEUTRAL)
    assert np.allclose(w, w[:, :1], atol=1e-6), w
    assert np.all(w <= 1.0)


def test_unclipped_pixels_are_only_white_balanced():
    rng = np.random.default_rng(3)
    px = rng.uniform(0.0, HIGHLIGHT_START - 0.01, (500, 3))
    w = balance_highlights(px, NEUTRAL)
    expect = np.minimum(px / NEUTRAL, 1.0)
    assert np.allclose(w, expect, atol=1e-6)


def test_the_blend_to_neutral_is_continuous():
    """Between HIGHLIGHT_START and HIGHLIGHT_FULL the colour fades to
    neutral without a jump."""
    levels = np.linspace(0.85, 1.0, 301)
    px = np.stack([levels, levels * 0.7, levels * 0.4], 1)
    w = balance_highlights(px, NEUTRAL)
    sat = w.max(1) - w.min(1)
    assert np.all(np.abs(np.diff(sat)) < 0.05)
    assert np.all(sat[levels >= HIGHLIGHT_FULL] < 1e-6) and sat[0] > 0.1


def test_shoulder_keeps_highlight_order_and_leaves_midtones():
    Y = np.linspace(0.0, 6.0, 601, dtype=np.float32)
    rgb = np.repeat(Y[:, None], 3, 1)
    out = highlight_shoulder(rgb.copy(), [0.2126, 0.7152, 0.0722], knee=0.75, peak=6.0)[:, 1]
    assert np.allclose(out[Y <= 0.75], Y[Y <= 0.75])
    assert np.all(np.diff(out) > 0) and out[-1] == pytest.approx(1.0, abs=1e-5)


def _patches() -> np.ndarray:
    """uint16 camera image (65535 = saturation) of clipped patches on a grey
    background under the NEUTRAL light."""
    img = np.empty((40, 60, 3), np.uint16)
    img[:] = np.rint(NEUTRAL * 0.3 * 65535)                     # grey card at 30 %
    img[:10, :20] = 65535                                        # all channels clipped
    img[:10, 20:40] = [65535, 64994, 65535]                      # the glint
    img[10:20, :20] = [65535, 40000, 20000]                      # red clipped
    img[10:20, 20:40] = [30000, 65535, 35000]                    # green clipped
    img[20:30, :20] = [20000, 50000, 65535]                      # blue clipped
    return img


@pytest.mark.parametrize("rendering", ["dng-matrix", "spectral"])
def test_clipped_patches_render_neutral_through_the_service(rendering, monkeypatch):
    from models import camera_names
    from recovery import Camera
    from service import metadata, pipeline
    from recovery.cameras import camera_from_matrix

    cm = np.array([[0.6880, -0.2475, -0.0487], [-0.3926, 1.2011, 0.1579], [-0.0892, 0.2006, 0.5815]])
    if rendering == "dng-matrix":
        cam = camera_from_matrix(cm)
        monkeypatch.setattr(metadata, "color_profile", lambda d: ColorProfile.from_matrix(cm))
    else:
        cam = Camera.named(camera_names()[0])
    run = pipeline.run_with_white(pipeline.EstimateRun(None, cam, []), NEUTRAL, "test")
    M, info = pipeline.correction_matrix(run, "D65", "sRGB", decoded=object())
    assert info["rendering"] == rendering
    img = _patches()
    out = pipeline.apply_matrix_inplace(img.copy(), M, info["encoding"], 8, neutral=info["neutral"]).astype(int)
    clipped = (img >= 0.98 * 65535).any(axis=-1)
    spread = out[clipped].max(1) - out[clipped].min(1)
    assert spread.max() <= 1, out[clipped][spread.argmax()]
    assert out[clipped].min() >= 250                             # and white, not grey
    # without the highlight handling the same pixels get a cast (what issue 13 saw)
    raw = pipeline.apply_matrix_inplace(img.copy(), M, info["encoding"], 8).astype(int)
    assert (raw[clipped].max(1) - raw[clipped].min(1)).max() > 20
