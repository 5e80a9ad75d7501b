"""Exports of a reconstruction result (:func:`jmocap.results.load_result`) to the files other
tools open (docs/formats.md):

* :mod:`jmocap.export.bvh`: Biovision hierarchy (BVH) motion (Blender, MotionBuilder, ...);
* :mod:`jmocap.export.opensim`: OpenSim's model (``.osim``), coordinates and ground reaction
  forces (``.mot`` + ExternalLoads ``.xml``) and markers (``.trc``);
* :mod:`jmocap.export.gltf`: an animated glTF 2.0 binary (``.glb``: Blender, three.js, Unity);
* :mod:`jmocap.export.viewer`: one self-contained HTML page that plays results in a browser.

Every writer is atomic (temp file + ``os.replace``) and takes the result's own character
(``jmocap.results.result_model``), so a subject-scaled reconstruction exports its own skeleton.
"""

from __future__ import annotations

import os
from pathlib import Path

from jmocap.export.bvh import Bvh, bvh_joint_positions, check_q, read_bvh, write_bvh

#: the formats of :func:`export_result` (``jmocap export --opensim --glb --bvh``)
EXPORT_FORMATS = ("opensim", "glb", "bvh")


def export_result(result: dict, name: str, out: str | os.PathLike, formats=EXPORT_FORMATS, *,
                  forces: bool = True) -> list[Path]:
    """Write one result (a :func:`jmocap.results.load_result` dict) in ``formats`` under the
    folder ``out`` (created): ``<name>.osim`` and the OpenSim data files, ``<name>.glb`` (with force
    arrows and contact markers unless ``forces`` is False), ``<name>.bvh``. Returns the paths."""
    from jmocap.results import result_model

    unknown = [f for f in formats if f not in EXPORT_FORMATS]
    if unknown:
        raise ValueError(f"unknown export formats {unknown} (known: {', '.join(EXPORT_FORMATS)})")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    if "opensim" in formats:
        from jmocap.export.opensim import write_opensim

        written += list(write_opensim(result, out, name).values())
    if "glb" in formats:
        from jmocap.export.gltf import write_glb

        written.append(write_glb(result, out / f"{name}.glb", forces=forces, contacts=forces))
    if "bvh" in formats:
        written.append(write_bvh(out / f"{name}.bvh", result_model(result), result["q"], result["fps"]))
    return written


__all__ = [
    "EXPORT_FORMATS",
    "export_result",
    "Bvh",
    "bvh_joint_positions",
    "check_q",
    "read_bvh",
    "write_bvh",
]
