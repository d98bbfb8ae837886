"""The estimator's own-uncertainty evidence tried for the confidence
(``benchmarks.flag_variants --leverage``; docs/confidence.md, "The
estimator's own uncertainty"): the leverage and the refits against their
direct formulas."""

import numpy as np

from benchmarks import flag_variants as V
from recovery import learned as L


class _Model:
    """The parts of :class:`recovery.learned.LearnedModel` the evidence reads; inputs = the flattened estimates."""

    def __init__(self, d, hidden=7, seed=3):
        rng = np.random.default_rng(seed)
        self.mean, self.scale = rng.normal(size=d), rng.uniform(0.5, 2.0, d)
        self.expansion = np.array([hidden, seed, 0.0])

    def inputs(self, f):
        return f.reshape(len(f), -1)


def _system(model, n=60, seed=0):
    rng = np.random.default_rng(seed)
    feats = rng.normal(size=(n, 3, 2))
    pw, pb = L.random_expansion(len(model.mean), int(model.expansion[0]), int(model.expansion[1]))
    Z = L.expand(model.inputs(feats), model.mean, model.scale, pw, pb)
    u = rng.uniform(0.2, 3.0, n)
    y = rng.normal(size=(n, 2))
    P = 2 * V.LEVERAGE_RIDGE * np.diag(np.r_[np.ones(Z.shape[1] - 1), 0.0])
    cam = rng.integers(0, 3, n)
    return {"Z": Z, "u": u, "y": y, "A": (Z * u[:, None]).T @ Z + P, "P": P, "cam": cam, "img": np.arange(n)}, P


def _evidence(n, seed):
    """The model, its system, ``n`` new inputs' evidence and their expanded features."""
    model = _Model(6)
    sy, P = _system(model)
    feats = np.random.default_rng(seed).normal(size=(n, 3, 2))
    ev = V.leverage_evidence(model, feats, np.arange(n), None, sy)
    pw, pb = L.random_expansion(6, 7, 3)
    phi = L.expand(model.inputs(feats), model.mean, model.scale, pw, pb)
    return model, sy, P, feats, ev, phi


def test_leverage_is_the_quadratic_form_of_the_inverse():
    model, sy, P, feats, ev, phi = _evidence(9, 5)
    direct = np.array([p @ np.linalg.inv(sy["A"]) @ p for p in phi])
    # a Cholesky solve against an explicit inverse of a matrix of condition < 1e6: agreement to ~1e-10 relative
    np.testing.assert_allclose(np.exp(ev["lev"][:, 0]), direct, rtol=1e-9)
    ZUZ = sy["A"] - P
    for r in (1.0, 10.0):
        d = np.array([p @ np.linalg.inv(ZUZ + P * r / V.LEVERAGE_RIDGE) @ p for p in phi])
        np.testing.assert_allclose(np.exp(ev[f"lev{r:g}"][:, 0]), d, rtol=1e-9)
    # far from the training inputs the leverage grows
    far = V.leverage_evidence(model, feats * 50, np.arange(9), None, sy)["lev"]
    assert np.median(far) > np.median(ev["lev"])


def test_camera_refits_are_the_refits_without_that_camera():
    model, sy, P, feats, ev, phi = _evidence(4, 6)
    Z, u, y = sy["Z"], sy["u"], sy["y"]

    def fit(m):
        Zu = Z[m] * u[m, None]
        return phi @ np.linalg.solve(Zu.T @ Z[m] + P, Zu.T @ y[m])

    full = fit(np.ones(len(u), bool))
    spread = np.sqrt(np.mean([((fit(sy["cam"] != c) - full) ** 2).sum(1) for c in range(3)], axis=0))
    np.testing.assert_allclose(ev["ens"][:, 0], np.log(spread + 1e-6), rtol=1e-8)
