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

from jmocap.export.bvh import Bvh, bvh_joint_positions, check_q, read_bvh, write_bvh

__all__ = [
    "Bvh",
    "bvh_joint_positions",
    "check_q",
    "read_bvh",
    "write_bvh",
]
