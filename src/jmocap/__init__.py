"""jmocap: physics-aware human motion capture from 2D keypoints, as pure JAX functions."""

from jmocap.layouts import CONTACT_SITES, LAYOUTS, Layout, get_layout
from jmocap.model import Model, load_model

__version__ = "0.1.0"

__all__ = ["CONTACT_SITES", "LAYOUTS", "Layout", "Model", "__version__", "get_layout", "load_model"]
