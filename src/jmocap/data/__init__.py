"""Clip data: the jmocap clip format, readers/writers of detector and dataset formats."""

from jmocap.data.clip import Clip, ClipFormatError, load_clip, save_clip

__all__ = ["Clip", "ClipFormatError", "load_clip", "save_clip"]
