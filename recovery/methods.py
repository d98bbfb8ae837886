"""The estimation methods and quality presets, by name: the one table the
API (:data:`recovery.api.ESTIMATORS`), ``GET /v1/models``, the REST form
fields, the batch options and the CLI's ``--method``/``--quality`` read.

Plain data, no numerical import: the CLI builds its ``--help`` from it
without loading numpy (``wandell --help`` stays light). Each method names
the estimator that runs it (``runs``, a key of
:data:`recovery.api.ESTIMATOR_KINDS`); adding a method is adding one entry
here (and, for a new kind of estimator, its function there).

>>> list(METHODS)[:4]
['auto', 'learned', 'bayes', 'maloney-wandell']
>>> METHODS["gray-world"].runs
'peer'
"""

from __future__ import annotations

from typing import NamedTuple

__all__ = ["Method", "METHODS", "METHOD_NAMES", "QUALITY_PRESETS", "QUALITY_NAMES"]


class Method(NamedTuple):
    """One estimation method: the kind of estimator that runs it, what it
    does (for the API's documentation) and the same in plain words (what the
    web page says of a result: "The light was estimated by WORDS.")."""

    runs: str
    description: str
    words: str = ""


#: Every estimation method, in the order the documentation lists them.
METHODS = {
    "auto": Method("auto", "the default: the learnt estimator (classical estimates combined by a network "
                           "learnt on real photographs, recovery.learned), or the light posterior for a scene of "
                           "uniform patches (a chart, a Mondrian) or a camera it cannot describe",
                   "the default choice"),
    "learned": Method("learned", "the learnt estimator whatever the scene",
                      "the learnt estimator (classical estimates combined by a model trained on 7,524 real "
                      "photographs of 12 cameras, through this camera's colour matrix)"),
    "bayes": Method("posterior", "the posterior over physically plausible lights (recovery.bayes), one light "
                                 "or a light map",
                    "the light posterior (the scene's surface colours weighed against a set of candidate lights)"),
    "maloney-wandell": Method("subspace", "the literal subspace method of Wandell (1985), eq. 30 and 35",
                              "the Maloney\u2013Wandell subspace method (under one light the surfaces' camera "
                              "responses lie in a plane whose normal fixes the light; Wandell 1985, eq. 30\u201335)"),
    "gray-world": Method("peer", "classical peer: the mean colour is grey (Buchsbaum 1980)",
                         "grey world (the mean of the scene is assumed grey)"),
    "white-patch": Method("peer", "classical peer: the brightest colour is white (max-RGB, Land & McCann 1971)",
                          "white patch (the brightest surface is assumed white)"),
    "shades-of-gray": Method("peer", "classical peer: the Minkowski p-norm mean (Finlayson & Trezzi 2004)",
                             "shades of grey (a Minkowski mean of the scene is assumed grey)"),
    "gray-edge": Method("peer", "classical peer: the mean edge is grey (van de Weijer et al. 2007)",
                        "grey edge (the mean image derivative is assumed grey)"),
}
METHOD_NAMES = tuple(METHODS)

#: The ``quality`` presets: points of the measured speed/accuracy trade
#: (``python -m benchmarks.tradeoff``; figures in docs/accuracy.md). Each sets the
#: analysis resolution (block-averaged pixels) and the wavelength grid.
QUALITY_PRESETS = {
    # fast pins one light: the light-map test costs more than its estimate
    "fast": {"analysis_pixels": 4096, "wavelength_step": 20.0, "spatial": False},
    "balanced": {"analysis_pixels": 65536, "wavelength_step": 10.0},
    "accurate": {"analysis_pixels": None, "wavelength_step": 10.0},
}
QUALITY_NAMES = tuple(QUALITY_PRESETS)
