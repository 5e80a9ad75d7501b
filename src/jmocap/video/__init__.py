"""Video input: from a video file to jmocap clips, reconstructions and an overlay video.

``jmocap video VIDEO OUTPUT`` (``jmocap.cli``) = :func:`extract_clips` (BlazePose on CPU,
tracking, flip repair, BODY_25 clips and camera sidecars) + ``jmocap reconstruct`` on them +
:func:`write_overlays`. Modules:

* :mod:`~jmocap.video.blazepose`: the BlazePose detector and landmark model (shipped in
  ``jmocap/assets/blazepose``, run by LiteRT), their pre- and post-processing;
* :mod:`~jmocap.video.tracking`: one track per person across frames (lost, bridged, split);
* :mod:`~jmocap.video.flips`: left/right flip repair over a track (two-state Viterbi);
* :mod:`~jmocap.video.mapping`: BlazePose-33 -> BODY_25;
* :mod:`~jmocap.video.reader`: frames streamed from a video file (ffmpeg);
* :mod:`~jmocap.video.extract`: the whole extraction and the overlays.

The packages it needs (LiteRT ``ai-edge-litert``, OpenCV, imageio-ffmpeg) are the optional
``video`` extra: ``pip install 'jmocap[video]'``. Importing this package needs none of them;
using it without them raises an ``ImportError`` saying so (:func:`missing_video_packages`
checks without importing). ``docs/formats.md``, "Video input", documents the route, the models'
provenance and the outputs.
"""

from __future__ import annotations

import importlib.util

from jmocap.video.blazepose import VIDEO_INSTALL

VIDEO_PACKAGES = ("ai_edge_litert", "cv2", "imageio_ffmpeg")  # import names


def missing_video_packages() -> list[str]:
    """The packages of the ``video`` extra that are not installed (import names), without importing them."""
    return [name for name in VIDEO_PACKAGES if importlib.util.find_spec(name) is None]


def __getattr__(name):  # the pipeline's names, imported on first use
    from jmocap.video import extract

    if name in extract.__all__:
        return getattr(extract, name)
    raise AttributeError(f"module 'jmocap.video' has no attribute {name!r}")


__all__ = ["VIDEO_INSTALL", "VIDEO_PACKAGES", "missing_video_packages", "choose_tracks", "extract_clips",
           "NoPersonError", "VideoOptions", "write_overlays"]
