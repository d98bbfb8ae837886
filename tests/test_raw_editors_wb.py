"""Issue 30, item 2: the white-balance comparison beside RawTherapee
(``python -m benchmarks.raw_editors``) measures the product's ``auto`` with
a learnt model that never saw the benchmark of the photograph.

No editor is needed here: the fold models' training sets (the training
procedure run on a small subset of the development photographs, every fit
watched), and the swap of the product's model (:func:`benchmarks.raw_editors.product_model`)
on a DNG through the product's own pipeline, restored afterwards.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from benchmarks import raw_editors as R
from benchmarks import train_illuminant as TI
from recovery import confidence as C
from recovery import learned as L

from .conftest import SHARED, unavailable

REAL = SHARED / "data" / "real"


def _small_set(per_benchmark: int = 40):
    from benchmarks.realdata import load_real

    if not (REAL / "cameras.json").is_file():
        unavailable(f"no development photographs at {REAL}")
    rs = load_real(REAL)
    rng = np.random.default_rng(0)
    sel = np.sort(np.concatenate([rng.choice(np.flatnonzero(rs.dataset == b), per_benchmark, replace=False)
                                  for b in rs.datasets]))
    return rs.subset(sel)


def test_fold_model_of_a_benchmark_never_fitted_on_its_photographs(monkeypatch):
    """Every fit of the training procedure (``build`` and each
    ``fit_model`` inside it: the inner selection, the calibration, the
    final fit) is watched while :func:`benchmarks.raw_editors.fold_models`
    runs; the model used for benchmark B is the one whose fits saw no
    photograph of B and saw both other benchmarks."""
    rs = _small_set()
    builds = []
    build, fit_model = TI.build, TI.fit_model

    def spy_build(rs_, feats, tuv, Ks, idx, *a, **k):
        rec = {"benchmarks": set(rs_.dataset[idx]), "fits": []}
        builds.append(rec)
        rec["model"] = build(rs_, feats, tuv, Ks, idx, *a, **k)
        return rec["model"]

    def spy_fit(feats, tuv, dataset, *a, **k):
        builds[-1]["fits"].append(set(dataset))
        return fit_model(feats, tuv, dataset, *a, **k)

    monkeypatch.setattr(TI, "build", spy_build)
    monkeypatch.setattr(TI, "fit_model", spy_fit)
    folds = R.fold_models(rs, log=lambda s: None)
    assert set(folds) == set(rs.datasets) and len(builds) == len(rs.datasets) == 3
    for b, model in folds.items():
        rec = [r for r in builds if np.array_equal(r["model"].coef, model.coef)]
        assert len(rec) == 1, f"the model used for {b} is not one the procedure built"
        rec = rec[0]
        others = set(rs.datasets) - {b}
        assert rec["benchmarks"] == others
        assert rec["fits"] and all(b not in f for f in rec["fits"]), f"a fit of {b}'s model saw {b}"
        assert set().union(*rec["fits"]) == others
        assert model.info["fold"] == {"left_out": b, "trained_on": [d for d in rs.datasets if d != b]}
        # the inner selection's record names the two training benchmarks only
        inner = model.info["selection"]["inner_mean_error_by_ridge"]
        assert all(set(v) == others for v in inner.values())
        assert model.flag is not None        # its own confidence and flag come with it
        assert f"fitted on {' and '.join(d for d in rs.datasets if d != b)} only" in R.model_text(model)


def _photo() -> dict:
    """A smooth, tinted synthetic scene (no uniform patches, so the
    product's ``auto`` is its learnt estimator) with an sRGB camera."""
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:64, 0:64] / 63.0
    base = np.stack([0.3 + 0.5 * x, 0.25 + 0.4 * y * (1 - x), 0.2 + 0.5 * (1 - y) * x], -1)
    img = np.clip(base * np.array([1.0, 0.8, 0.55]) + rng.normal(0, 0.03, base.shape), 0.02, 0.95)
    srgb_to_xyz = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
    return {"image": img, "matrix": np.linalg.inv(srgb_to_xyz)}


def test_product_model_swaps_the_learnt_model_and_restores_the_shipped_one(tmp_path):
    """Inside :func:`benchmarks.raw_editors.product_model` the product's
    ``auto`` (through :func:`service.pipeline.analyze` on a DNG) runs with
    the given model and its flag; on leaving, even on an error, the
    shipped model and flag are back and give the first answer again,
    bit for bit."""
    dng = tmp_path / "a.dng"
    R.write_photo_dng(str(dng), _photo())
    data = dng.read_bytes()
    shipped, shipped_flag = L.load_model(), C.load_flag_model()
    assert set(shipped.info["benchmarks"]) == set(R.SET_NAMES.values())
    before = R.product_light(data, "auto")
    # the model's learnt map set to zero: the reference estimate stands, a different light
    other = dataclasses.replace(shipped, coef=np.zeros_like(shipped.coef),
                                flag=dataclasses.replace(shipped_flag, threshold=0.123))
    with R.product_model(other):
        assert L.load_model() is other and C.load_flag_model() is other.flag
        inside = R.product_light(data, "auto")
    assert R.angle(inside, before) > 0.05, "the swapped model did not reach the product's estimate"
    assert L.load_model().info == shipped.info and np.array_equal(L.load_model().coef, shipped.coef)
    assert C.load_flag_model().to_json() == shipped_flag.to_json() != other.flag.to_json()
    np.testing.assert_array_equal(R.product_light(data, "auto"), before)
    with pytest.raises(RuntimeError), R.product_model(other):
        raise RuntimeError("inside")
    assert L.load_model() is not other and np.array_equal(L.load_model().coef, shipped.coef)
    with R.product_model(None):            # the shipped model: nothing swapped
        assert np.array_equal(L.load_model().coef, shipped.coef)
