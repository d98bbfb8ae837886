"""The kind of spectrum the light posterior (``method="bayes"``) reports
(issue 19 item 5): a plausible light for the scene, daylight or Planckian
unless the evidence says otherwise.

The posterior mass per kind was the rule and put fluorescent spectra on 61 %
of real photographs whose measured light is near the Planckian locus
(``python -m benchmarks.bayes_spectra``, 30 per camera: 334 such images):
over a discrete candidate set the posterior collapses onto whichever lamp
sits at the estimate's chromaticity, and through a matrix-derived camera the
measured daylights sit as far from the daylight and Planckian loci as the
fluorescent lamps do. The kind is now decided by what the image's colours
say at the estimate's chromaticity (:func:`recovery.bayes.kind_evidence`):
93 % daylight or Planckian on those 334 images (per camera 79-100 %), while
Mondrians under CIE FL2, FL4, FL10 and FL11 seen by cameras with measured
sensitivities mostly stay fluorescent (88 % of 96; the mass rule 93 %).
"""

from __future__ import annotations

import numpy as np
import pytest

from recovery import Camera
from recovery.api import estimate_illuminant
from recovery.bayes import KIND_EVIDENCE_NATS
from recovery.illuminant_prior import SMOOTH_KINDS
from testing.scenes import mondrian_scene

from .conftest import unavailable


@pytest.fixture(scope="module")
def real(load_real_once):
    from benchmarks.realdata import BENCHMARKS, REAL_DIR

    missing = [f for f in (*BENCHMARKS.values(), "cameras.json") if not (REAL_DIR / f).is_file()]
    if missing:
        unavailable(f"{REAL_DIR} lacks {missing} (the development photographs are not next to the project)")
    return load_real_once(REAL_DIR)       # loaded once a session (test_learned uses them too)


def test_real_photographs_near_the_locus_get_smooth_spectra(real):
    """5 photographs per camera (seed 1, not the benchmark's), those whose
    measured light has |Duv| < 0.01: at least 80 % daylight or Planckian.
    Measured 93 % on 334 such images (before: 34 %); for ~55 images the
    binomial standard deviation at 93 % is 3.4 points, so 80 % is over 3
    below the measurement and far above the old rule."""
    from benchmarks.bayes_spectra import true_duv
    from benchmarks.realdata import usable_mask
    from recovery.cameras import camera_from_matrix

    rs = real
    rng = np.random.default_rng(1)
    fam, cams = [], {}
    for c in rs.cameras:
        for i in rng.choice(np.flatnonzero(rs.camera == c), 5, replace=False):
            if abs(true_duv(rs.truth[i], rs.matrices[c])) >= 0.01:
                continue
            if c not in cams:
                cams[c] = camera_from_matrix(rs.matrices[c]).with_color_matrix(rs.matrices[c])
            im = rs.images[i].astype(float)
            est = estimate_illuminant(np.where(usable_mask(im)[..., None], im, 0), cams[c], "bayes",
                                      white_level=1.0)
            if est.method != "bayes":
                continue
            d = est.diagnostics
            assert d["spectrum_rule"] and d["spectrum_kind_evidence"]
            fam.append(d["spectrum_family"])
    assert len(fam) >= 40
    smooth = np.mean([f in SMOOTH_KINDS for f in fam])
    assert smooth >= 0.8, (smooth, fam)


CAMERAS = ("Nikon 5100 (NPL)", "Canon EOS 5D Mark II")


def _families(lights, seeds):
    out = []
    for camera in CAMERAS:
        cam = Camera.named(camera)
        for light in lights:
            for seed in seeds:
                sc = mondrian_scene(np.random.default_rng(seed), 24, camera, light, 64)
                out.append((light, estimate_illuminant(sc.image, cam, method="bayes").diagnostics))
    return out


def test_fluorescent_mondrians_still_report_fluorescent():
    """Under real fluorescent lamps, with the cameras' measured
    sensitivities, the colours say so at the estimate's chromaticity: 24
    Mondrians (CIE FL2, FL4, FL10, FL11; 2 cameras; seeds 12-14, not the
    benchmark's; 24 of 24 fluorescent). Measured on the benchmark's 96
    (seeds 0-11): 88 % fluorescent (FL2 79 %, FL11 88 %, FL4 96 %, FL10
    88 %; the posterior-mass rule 93 %), a few high-pressure; a scene whose
    surfaces render alike under both (seed 6) stays daylight. At n = 24 the
    binomial standard deviation at 88 % is 7 points: at least 75 %."""
    ds = [d for _, d in _families(("FL2", "FL4", "FL10", "FL11"), (12, 13, 14))]
    fl = [d for d in ds if d["spectrum_family"] == "fluorescent"]
    assert len(fl) >= 0.75 * len(ds), [d["spectrum_rule"] for d in ds if d["spectrum_family"] != "fluorescent"]
    for d in fl:
        assert d["best_candidate"].startswith("FL"), d["spectrum_rule"]
        assert f"at least {KIND_EVIDENCE_NATS:g}" in d["spectrum_rule"]
        assert d["spectrum_kind_colours_nats"] >= KIND_EVIDENCE_NATS


def test_smooth_mondrians_report_daylight_or_planckian():
    """Under D50, D65, D75 and A the right smooth kind (measured on the
    benchmark's 96 scenes: 93 %, the posterior-mass rule 96 %; the others
    mostly the white LED LED-B5 or the broadband FL7/FL8, near daylight):
    at least 80 % of 24 scenes (seeds 12-14: 22 of 24), the rule saying the
    colours do not say a spiky light."""
    res = _families(("D50", "D65", "D75", "A"), (12, 13, 14))
    ok = [d for light, d in res if d["spectrum_family"] == ("planckian" if light == "A" else "daylight")]
    assert len(ok) >= 0.8 * len(res), [(light, d["spectrum_rule"]) for light, d in res]
    assert all("do not say a spiky light" in d["spectrum_rule"] for d in ok)
