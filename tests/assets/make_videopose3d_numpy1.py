"""Writes tests/assets/videopose3d_numpy1_p{2,3,5}.npz with numpy 1.x: run under numpy 1.26 as
``python make_videopose3d_numpy1.py tests/assets`` (test_format_hardening.py reads them).

positions_2d = {"S9": {"Walking 1": [cam c: float32 (3, 17, 2) = arange + 1 + 1000 c, c < 4]},
                "S11": {"Sitting": [float64 (2, 17, 2) = arange + 0.5]}}
metadata = {"layout_name": "h36m", "num_joints": np.int64(17),
            "keypoints_symmetry": [[4, 5, 6, 11, 12, 13], [1, 2, 3, 14, 15, 16]]}
p3: np.savez_compressed (pickle protocol 3, numpy 1.x's default); p2, p5: the same members
written as np.save does (format 1.0 header + pickle.dump) at protocols 2 and 5.
"""
import io
import pickle
import sys
import zipfile

import numpy as np
from numpy.lib import format as F

assert np.__version__.startswith("1."), np.__version__
n = 3 * 17 * 2
positions = {
    "S9": {"Walking 1": [np.arange(n, dtype=np.float32).reshape(3, 17, 2) + 1 + 1000 * c for c in range(4)]},
    "S11": {"Sitting": [np.arange(2 * 17 * 2, dtype=np.float64).reshape(2, 17, 2) + 0.5]},
}
metadata = {"layout_name": "h36m", "num_joints": np.int64(17),
            "keypoints_symmetry": [[4, 5, 6, 11, 12, 13], [1, 2, 3, 14, 15, 16]]}
out = sys.argv[1]
np.savez_compressed(f"{out}/videopose3d_numpy1_p3.npz", positions_2d=positions, metadata=metadata)
for proto in (2, 5):
    with zipfile.ZipFile(f"{out}/videopose3d_numpy1_p{proto}.npz", "w", zipfile.ZIP_DEFLATED) as z:
        for name, value in (("positions_2d", positions), ("metadata", metadata)):
            b = io.BytesIO()
            F.write_array_header_1_0(b, {"descr": "|O", "fortran_order": False, "shape": ()})
            pickle.dump(np.array(value, dtype=object), b, protocol=proto)
            z.writestr(name + ".npy", b.getvalue())
