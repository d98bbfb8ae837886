"""Build the two data files of the surface prior (issue 31), recording where they came from.

``models/data/camera_set_rawtoaces.npz``
    The 47 measured cameras of ``../shared/data/cameras`` (Academy Software
    Foundation ``rawtoaces-data`` commit e9b8503, Apache-2.0, licence text in
    ``models/data/camera_set_rawtoaces.LICENSE``; measured by Weta Digital
    2025-26 and by the Academy 2017), float32 on their own grid (380-780 nm
    at 5 nm), each camera's channels kept with their measured balance and
    scaled so its largest value is 1.
``models/data/surface_sets.npz``
    The measured reflectance sets colour-science ships (BSD-3-Clause
    package; the data's own terms in ``docs/surfaces.md``), float32 on
    380-780 nm at 5 nm, each row labelled with its set: so that the service
    does not import colour-science to build the prior.

The product reads only the ``.npz`` files (:mod:`models.surface_data`).
Run: ``python -m benchmarks.build_prior_data``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CAMERAS = ROOT / ".." / "shared" / "data" / "cameras" / "rawtoaces"
GRID = np.arange(380.0, 781.0, 5.0)


def build_cameras() -> None:
    out = ROOT / "models" / "data" / "camera_set_rawtoaces.npz"
    names, sens, who = [], [], []
    for f in sorted(CAMERAS.glob("*.json")):
        d = json.loads(f.read_text())
        data = d["spectral_data"]["data"]["main"]
        wl = np.array(sorted(map(int, data)), float)
        assert np.allclose(wl, GRID), f.name
        r = np.array([data[str(int(w))] for w in wl], float)
        names.append(f"{d['header']['manufacturer']} {d['header']['model']}")
        who.append(f"{d['header'].get('document_creator', '?')}; licence {d['header'].get('license', '?')}")
        sens.append(r / r.max())
    np.savez_compressed(out, wavelengths=GRID.astype(np.float32), sensitivities=np.array(sens, np.float32),
                        names=np.array(names), measured_by=np.array(who),
                        source=np.array("Academy Software Foundation rawtoaces-data (commit e9b8503) as copied to "
                                        "shared/data/cameras; Apache-2.0"))
    print(f"{len(names)} cameras -> {out} ({out.stat().st_size} bytes)")


def build_surfaces() -> None:
    import colour

    from models._colour import sd_to_array

    out = ROOT / "models" / "data" / "surface_sets.npz"
    sets = {
        "colorchecker": [colour.SDS_COLOURCHECKERS["BabelColor Average"]],
        "rawtoaces-190": None,
        "tcs": [colour.quality.SDS_TCS["CIE 2024"]],
        "vs": [colour.quality.SDS_VS["NIST CQS 9.0"]],
        "pmc": [colour.SDS_COLOURCHECKERS["PMC"]],
    }
    rows, labels, names = [], [], []
    for name, groups in sets.items():
        if groups is None:
            msds = colour.characterisation.read_training_data_rawtoaces_v1()
            arr = sd_to_array(msds, GRID).T
            rows.append(arr)
            labels += [name] * len(arr)
            names += [f"{name} {k}" for k in msds.labels]
            continue
        for sds in groups:
            for k, sd in sds.items():
                rows.append(sd_to_array(sd, GRID)[None]), labels.append(name), names.append(f"{name} {k}")
    R = np.clip(np.concatenate(rows), 0.0, None)
    np.savez_compressed(out, wavelengths=GRID.astype(np.float32), reflectances=R.astype(np.float32),
                        set=np.array(labels), names=np.array(names),
                        source=np.array(f"colour-science {colour.__version__}: SDS_COLOURCHECKERS['BabelColor "
                                        "Average'], read_training_data_rawtoaces_v1(), quality.SDS_TCS['CIE 2024'], "
                                        "quality.SDS_VS['NIST CQS 9.0'], SDS_COLOURCHECKERS['PMC']"))
    print(f"{len(R)} surfaces in {len(sets)} sets -> {out} ({out.stat().st_size} bytes)")


if __name__ == "__main__":
    build_cameras()
    build_surfaces()
