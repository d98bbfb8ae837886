"""Physically plausible lights: the candidate set and prior of the Bayesian
illuminant estimator (:mod:`recovery.bayes`).

The light is not any vector of camera space: it is the spectrum of a real
source. Following the issue's first direction, the estimator searches a set
of candidate spectra built from colour-science's data only:

* ``named``: every illuminant colour-science ships (CIE A, B, C, the D
  series, E, FL1-FL12, FL3.x, HP, LED, ...), the lights of
  :func:`models.illuminant_names`;
* ``daylight``: the CIE daylight locus (Judd, MacAdam & Wyszecki's S0, S1,
  S2 basis, CIE 015:2018), evenly spaced in reciprocal colour temperature
  from 4000 K to 25000 K (its domain of definition);
* ``blackbody``: Planckian radiators from 1600 K to 12000 K, evenly spaced
  in reciprocal colour temperature;
* ``mixture``: two-light mixtures that occur in practice (daylight through a
  window plus tungsten or fluorescent room light, warm plus cool light), at
  power fractions 1/4, 1/2 and 3/4 of unit-mean spectra;
* ``narrowband``: sodium-like and single-LED lamps, a Gaussian emission band
  (25 nm wide, centred every 20 nm from 440 to 660 nm) over a weak 3000 K
  broadband floor: under such light every surface takes nearly the light's
  own colour, a case no other family covers.

Each candidate is a spectrum (unit mean power) on the caller's grid, so any
camera sees each one exactly (eq. 12 of Wandell 1985): nothing here is tied
to a camera. Mixtures of lights are lights, so a posterior mean over
candidates (:mod:`recovery.bayes`) is itself a physically realisable light.

The prior gives every family the same total mass (narrow-band lamps a
quarter of it) and spreads it evenly over the family's members, so that a
family with many near-identical members (fifteen FL3.x lamps) does not
dominate by count alone. colour-science's ``SDS_LIGHT_SOURCES`` (56 lamps)
are deliberately *not* candidates: they serve as unseen lights when checking
that the estimator generalises.

References
----------
Wandell (1985) [docs/references.md#seed-002]: eq. 5 and 10 (lights as weighted sums
of basis functions; the daylight basis of Judd, MacAdam & Wyszecki 1964).
CIE 015:2018 (daylight locus, Planck's law).
Brainard & Freeman (1997), Bayesian color constancy, JOSA A 14(7): a prior
over physically realisable lights.
Finlayson, Hordley & Hubel (2001), Color by correlation, IEEE PAMI 23(11):
a discrete set of plausible lights scored against the image.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

import models

__all__ = ["CandidateLights", "FAMILIES", "default_candidates", "candidate_lights", "random_lights"]

#: The candidate families, in order.
FAMILIES = ("named", "daylight", "blackbody", "mixture", "narrowband")

#: Prior mass of each family (relative): narrow-band lamps are admitted but
#: rare.
FAMILY_WEIGHTS = {"named": 1.0, "daylight": 1.0, "blackbody": 1.0, "mixture": 1.0, "narrowband": 0.25}

#: (light a, light b) pairs mixed at power fractions of ``MIXTURE_FRACTIONS``.
MIXTURE_PAIRS = (("D65", "A"), ("D50", "A"), ("D75", "BB2700"), ("D65", "BB2000"), ("D65", "FL2"),
                 ("D50", "FL11"), ("A", "FL4"), ("D65", "LED-B3"), ("BB3000", "LED-B5"), ("D75", "FL7"))
MIXTURE_FRACTIONS = (0.25, 0.5, 0.75)


@dataclass(frozen=True)
class CandidateLights:
    """A discrete set of plausible lights and their prior.

    Attributes
    ----------
    wavelengths : (N,) nm
    spectra : (M, N) relative spectral power, each with unit mean
    names : tuple of M str
    families : tuple of M str (``named``, ``daylight``, ``blackbody``,
        ``mixture`` or ``user``)
    prior : (M,) prior probabilities, summing to 1
    """

    wavelengths: np.ndarray
    spectra: np.ndarray
    names: tuple
    families: tuple
    prior: np.ndarray

    def __post_init__(self):
        wl = np.asarray(self.wavelengths, float)
        sp = np.atleast_2d(np.asarray(self.spectra, float))
        pr = np.asarray(self.prior, float)
        if sp.shape[1] != wl.size:
            raise ValueError(f"spectra must be (M, {wl.size}), got {sp.shape}")
        if len(self.names) != sp.shape[0] or len(self.families) != sp.shape[0] or pr.shape != (sp.shape[0],):
            raise ValueError("names, families and prior must have one entry per spectrum")
        if not (np.all(np.isfinite(sp)) and np.all(np.isfinite(pr))):
            raise ValueError("candidate spectra and prior must be finite")
        if np.any(sp < 0) or np.any(sp.sum(axis=1) <= 0):
            raise ValueError("candidate spectra must be non-negative with positive power")
        if np.any(pr < 0) or pr.sum() <= 0:
            raise ValueError("prior must be non-negative with a positive sum")
        sp = sp / sp.mean(axis=1, keepdims=True)
        for a in (wl, sp):
            a.flags.writeable = False
        object.__setattr__(self, "wavelengths", wl)
        object.__setattr__(self, "spectra", sp)
        object.__setattr__(self, "prior", pr / pr.sum())
        object.__setattr__(self, "names", tuple(str(n) for n in self.names))
        object.__setattr__(self, "families", tuple(str(f) for f in self.families))
        h = hashlib.sha1()
        for a in (wl, sp, self.prior):
            h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
        h.update("\0".join(self.names).encode())
        object.__setattr__(self, "_key", h.hexdigest())

    def __len__(self) -> int:
        return int(self.spectra.shape[0])

    @property
    def key(self) -> str:
        """A digest of the spectra, names and prior (for caches)."""
        return self._key

    def select(self, keep) -> "CandidateLights":
        """The candidates where ``keep`` (boolean (M,) or a predicate on
        ``(name, family)``) is true, prior renormalised."""
        if callable(keep):
            keep = [bool(keep(n, f)) for n, f in zip(self.names, self.families)]
        k = np.asarray(keep, bool)
        if not k.any():
            raise ValueError("no candidate left")
        idx = np.flatnonzero(k)
        return CandidateLights(self.wavelengths, self.spectra[idx], tuple(self.names[i] for i in idx),
                               tuple(self.families[i] for i in idx), self.prior[idx])


def _mireds(lo_k: float, hi_k: float, step_mired: float) -> np.ndarray:
    """Temperatures (K) evenly spaced in reciprocal temperature."""
    m = np.arange(1e6 / hi_k, 1e6 / lo_k + 1e-9, step_mired)
    return 1e6 / m


def _family_prior(families, weights=None) -> np.ndarray:
    fam = np.asarray(families)
    names = list(dict.fromkeys(families))
    w = {f: 1.0 for f in names} if weights is None else {f: float(weights.get(f, 0.0)) for f in names}
    pr = np.zeros(fam.size)
    for f in names:
        sel = fam == f
        pr[sel] = w[f] / sel.sum()
    return pr


@lru_cache(maxsize=16)
def _default_cached(wl: tuple, families: tuple, exclude: tuple, daylight_step: float, blackbody_step: float,
                    family_weights: tuple | None):
    wl = np.asarray(wl)
    spectra, names, fams = [], [], []

    def add(name, spd, fam):
        spd = np.clip(np.asarray(spd, float), 0.0, None)
        if spd.mean() <= 0 or name in exclude:
            return
        spectra.append(spd / spd.mean())
        names.append(name)
        fams.append(fam)

    if "named" in families:
        for n in models.illuminant_names():
            add(n, models.illuminant(n, wl), "named")
    if "daylight" in families:
        for t in _mireds(4000.0, 25000.0, daylight_step):
            add(f"daylight {t:.0f} K", models.daylight(float(t), wl), "daylight")
    if "blackbody" in families:
        for t in _mireds(1600.0, 12000.0, blackbody_step):
            add(f"blackbody {t:.0f} K", models.blackbody(float(t), wl), "blackbody")
    if "mixture" in families:
        for a, b in MIXTURE_PAIRS:
            ea, eb = models.illuminant(a, wl), models.illuminant(b, wl)
            for f in MIXTURE_FRACTIONS:
                add(f"{f:g} {a} + {1 - f:g} {b}", f * ea + (1 - f) * eb, "mixture")
    if "narrowband" in families:
        # sodium-like and single-LED lights: a Gaussian emission band over a
        # weak broadband floor (a tenth of the power from a 3000 K radiator)
        bb = models.blackbody(3000.0, wl)
        bb = bb / bb.mean()
        for centre in np.arange(440.0, 661.0, 20.0):
            band = np.exp(-0.5 * ((wl - centre) / (25.0 / 2.355)) ** 2)
            band = band / band.mean()
            add(f"band {centre:.0f} nm", 0.9 * band + 0.1 * bb, "narrowband")
    if not spectra:
        raise ValueError("no candidate lights: every family was excluded")
    weights = None if family_weights is None else dict(family_weights)
    return CandidateLights(wl, np.stack(spectra), tuple(names), tuple(fams), _family_prior(fams, weights))


def default_candidates(wavelengths=None, *, families=FAMILIES, exclude=(), daylight_step_mired: float = 10.0,
                       blackbody_step_mired: float = 20.0, family_weights: dict | None = None) -> CandidateLights:
    """The default set of plausible lights on ``wavelengths`` (cached).

    Parameters
    ----------
    wavelengths : (N,) nm, default the project grid (400-700 nm at 10 nm)
    families : which of :data:`FAMILIES` to include
    exclude : candidate names to leave out (for held-out checks)
    daylight_step_mired, blackbody_step_mired : spacing of the loci in
        reciprocal megakelvin (10 mired is about the just-noticeable
        difference of colour temperature near 6500 K)
    family_weights : relative prior mass per family (default
        :data:`FAMILY_WEIGHTS`: equal, narrow-band a quarter)

    Returns
    -------
    CandidateLights

    Examples
    --------
    >>> c = default_candidates()
    >>> len(c) > 100, sorted(set(c.families)) == sorted(FAMILIES)
    (True, True)
    """
    wl = models.DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    bad = [f for f in families if f not in FAMILIES]
    if bad:
        raise ValueError(f"unknown families {bad}; accepted: {list(FAMILIES)}")
    fw = tuple(sorted((FAMILY_WEIGHTS if family_weights is None else family_weights).items()))
    return _default_cached(tuple(wl.tolist()), tuple(families), tuple(exclude), float(daylight_step_mired),
                           float(blackbody_step_mired), fw)


def candidate_lights(spectra, wavelengths, names=None, prior=None) -> CandidateLights:
    """A user's own candidate set: ``(M, N)`` spectra on ``wavelengths``
    (uniform prior unless given)."""
    sp = np.atleast_2d(np.asarray(spectra, float))
    m = sp.shape[0]
    names = tuple(names) if names is not None else tuple(f"light {i}" for i in range(m))
    prior = np.full(m, 1.0 / m) if prior is None else np.asarray(prior, float)
    return CandidateLights(np.asarray(wavelengths, float), sp, names, ("user",) * m, prior)


def random_lights(rng: np.random.Generator, n: int, wavelengths=None) -> tuple[np.ndarray, list[str]]:
    """Random plausible lights *not* in the default set, for held-out checks:
    a daylight (4000-20000 K) or a blackbody (2000-8000 K) at a random
    temperature, mixed with a random second such light at a random power
    fraction. Returns ``(n, N)`` unit-mean spectra and their descriptions."""
    wl = models.DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    out, names = [], []

    def one():
        if rng.random() < 0.5:
            t = float(1e6 / rng.uniform(1e6 / 20000, 1e6 / 4000))
            return models.daylight(t, wl), f"daylight {t:.0f} K"
        t = float(1e6 / rng.uniform(1e6 / 8000, 1e6 / 2000))
        return models.blackbody(t, wl), f"blackbody {t:.0f} K"

    for _ in range(n):
        a, na = one()
        b, nb = one()
        f = float(rng.uniform(0, 1))
        spd = f * a / a.mean() + (1 - f) * b / b.mean()
        out.append(spd / spd.mean())
        names.append(f"{f:.2f} {na} + {1 - f:.2f} {nb}")
    return np.stack(out), names


# --------------------------------------------------------------------------- kinds of light
#: Kinds of light whose spectrum is smooth (no emission lines): a reported
#: spectrum is one of these unless the evidence says otherwise
#: (:func:`recovery.bayes.plausible_spectrum`).
SMOOTH_KINDS = ("daylight", "planckian")

_NAMED_KIND = {"B": "daylight", "C": "daylight", "E": "planckian", "A": "planckian",
               "ISO 7589 Photographic Daylight": "daylight", "ISO 7589 Studio Tungsten": "planckian",
               "ISO 7589 Photoflood": "planckian"}


def _name_kind(name: str) -> str:
    n = name.strip()
    if n in _NAMED_KIND:
        return _NAMED_KIND[n]
    if n.startswith(("daylight", "ID")) or (n.startswith("D") and n[1:].isdigit()):
        return "daylight"
    if n.startswith(("blackbody", "BB")):
        return "planckian"
    if n.startswith("FL"):
        return "fluorescent"
    if n.startswith("LED"):
        return "LED"
    if n.startswith("HP"):
        return "high-pressure"
    if n.startswith("band"):
        return "narrowband"
    return "other"


def light_kinds(name: str, family: str) -> list[tuple[str, float]]:
    """The physical kind(s) of a candidate light as ``[(kind, share)]``:
    ``daylight`` (the CIE daylight locus, D-series, B, C), ``planckian``
    (blackbody radiators, A, E, tungsten), ``fluorescent``, ``LED``,
    ``high-pressure``, ``narrowband``, ``user`` or ``other``; a two-light
    mixture ``"f a + g b"`` shares its mass between its lights' kinds by
    power fraction."""
    if family == "daylight":
        return [("daylight", 1.0)]
    if family == "blackbody":
        return [("planckian", 1.0)]
    if family == "narrowband":
        return [("narrowband", 1.0)]
    if family == "user":
        return [("user", 1.0)]
    if family == "mixture":
        out = []
        for part in name.split(" + "):
            f, _, light = part.strip().partition(" ")
            try:
                out.append((_name_kind(light), float(f)))
            except ValueError:
                return [("other", 1.0)]
        return out
    return [(_name_kind(name), 1.0)]
