"""The light posterior's evidence tried for the confidence
(``benchmarks.flag_variants --bayes``; docs/confidence.md, "The light
posterior's width"): its estimate in the learnt estimator's log-chroma, its
width, the cache, and the disagreement with a learnt answer."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks import flag_variants as V
from recovery import learned as L
from recovery.metrics import angular_error

from .conftest import unavailable


@pytest.fixture(scope="module")
def photos(load_real_once):
    from benchmarks.realdata import BENCHMARKS, REAL_DIR

    missing = [f for f in (*BENCHMARKS.values(), "cameras.json") if not (REAL_DIR / f).is_file()]
    if missing:
        unavailable(f"{REAL_DIR} lacks {missing} (the development photographs are not next to the project)")
    rs = load_real_once(REAL_DIR)
    # two photographs of each benchmark (seed 7), each benchmark's camera matrices as they are
    rng = np.random.default_rng(7)
    rows = np.concatenate([rng.choice(np.flatnonzero(rs.dataset == b), 2, replace=False) for b in rs.datasets])
    return rs.subset(rows)


def test_the_posterior_is_read_in_the_learnt_estimators_log_chroma(photos, tmp_path):
    from benchmarks.realdata import usable_mask
    from recovery.bayes import estimate_bayes
    from recovery.cameras import camera_from_matrix

    Ks = {k: L.canonical_transform(m, L.BRADFORD) for k, m in photos.matrices.items()}
    cache = tmp_path / "bayes.npz"
    bz = V.bayes_evidence(photos, Ks, cache, log=lambda s: None)
    assert cache.is_file()
    for i in range(len(photos.truth)):
        cam = camera_from_matrix(photos.matrices[photos.camera[i]])
        rgb, spectrum, diag = estimate_bayes(photos.images[i], usable_mask(photos.images[i]), cam)
        assert spectrum is not None           # these photographs have plenty of colours: no fallback
        np.testing.assert_allclose(bz["uv"][i], L.rgb_to_uv(Ks[photos.camera[i]] @ rgb), atol=1e-9)
        np.testing.assert_allclose(bz["w"][i, 0], np.log(diag["posterior_spread_deg"] + 0.05), atol=1e-9)
        c = diag["confidence"]
        np.testing.assert_allclose(bz["w"][i, 2], np.log(c / (1 - c)), atol=1e-9)
    # a light estimate: the posterior's median error on these benchmarks is 2.8-3.7 degrees, worst 25 % above 6
    ang = angular_error(L.uv_to_rgb(bz["uv"]), np.stack([Ks[c] @ t for t, c in zip(photos.truth, photos.camera)]))
    assert np.median(ang) < 10
    # the cache gives the same evidence without estimating again
    again = V.bayes_evidence(photos, Ks, cache, log=lambda s: None)
    for k in ("uv", "w"):
        np.testing.assert_array_equal(again[k], bz[k])


def test_the_disagreement_is_the_log_distance_to_the_learnt_answer():
    class _Model:
        mean, scale = np.zeros(4), np.ones(4)

        def inputs(self, f):
            return f.reshape(len(f), -1)

    rng = np.random.default_rng(0)
    feats = rng.normal(size=(5, 2, 2))
    uv = rng.normal(size=(5, 2))
    bz = {"uv": uv + [[0.1, 0.0], [0.0, 0.2], [0.03, 0.04], [0.0, 0.0], [np.nan, np.nan]], "w": rng.normal(size=(5, 3))}
    ev = V.extra_evidence(_Model(), feats, np.arange(5), uv, np.arange(5), bz=bz)
    expected = np.log(np.array([0.1, 0.2, 0.05, 0.0, 1.0]) + V._FLOOR)   # a fallback (NaN) counts as far
    np.testing.assert_allclose(ev["bd"][:, 0], expected, atol=1e-12)
    np.testing.assert_array_equal(ev["bw"], bz["w"])
