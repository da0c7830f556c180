"""li2018 exponential-map CSV -> BVH: the conversion behind ``mocap/cmu_li2018`` (data README, "How the CSV was read").

Input: one CSV of Li et al. (CVPR 2018), ``data/cmu_mocap/<split>/<action>/<name>.txt`` in
github.com/chaneyddtt/Convolutional-Sequence-to-Sequence-Model-for-Human-Dynamics. One frame per line, 117 values:
the root position (X, Y, Z in CMU ASF units), then 38 exponential maps (radians), one per node of the cgspeed CMU
skeleton in depth-first order (31 joints and 7 end sites). Line 0 is the CMU T-pose reference frame: it is dropped,
so BVH frame k is CSV line k + 1.

Output: a BVH with one fixed skeleton (the repository's ASF offsets, ``_some_variables`` without its display factor
70, times 0.0254/0.45 m), 120 Hz, root channels ``X/Y/Zposition Zrotation Xrotation Yrotation`` and
``Zrotation Xrotation Yrotation`` elsewhere (R = Rz·Rx·Ry, intrinsic, degrees). The repository's ``fkl`` multiplies
row vectors, so a joint's local rotation in column form is Rodrigues(r)ᵀ. Angles are unwrapped in time and printed with
six decimals, a negative zero as ``0.000000``.

The Euler angles are taken from the matrix entries by hand, not with scipy's ``as_euler``: at a middle angle past 90°
the first and third angles are ±180°, and this formula gives the signs of the stored files (scipy picks the other
sign in one of the 96 files). Every stored file is reproduced byte for byte.
"""

from __future__ import annotations

import numpy as np

METRES_PER_ASF_UNIT = 0.0254 / 0.45
FRAME_TIME_S = "0.0083333333"  # 120 Hz, as written in the stored files
VALUES_PER_ROW = 117

# (name, parent index, offset in ASF units); name None is an end site. Depth-first order of the CSV's 38 nodes.
SKELETON: tuple[tuple[str | None, int, tuple[float, float, float]], ...] = (
    ("root", -1, (0.0, 0.0, 0.0)),
    ("lhipjoint", 0, (0.0, 0.0, 0.0)),
    ("lfemur", 1, (1.65674, -1.80282, 0.62477)),
    ("ltibia", 2, (2.5972, -7.13576, 0.0)),
    ("lfoot", 3, (2.49236, -6.8477, 0.0)),
    ("ltoes", 4, (0.19704, -0.54136, 2.14581)),
    (None, 5, (0.0, 0.0, 1.11249)),
    ("rhipjoint", 0, (0.0, 0.0, 0.0)),
    ("rfemur", 7, (-1.6107, -1.80282, 0.62476)),
    ("rtibia", 8, (-2.59502, -7.12977, 0.0)),
    ("rfoot", 9, (-2.4678, -6.78024, 0.0)),
    ("rtoes", 10, (-0.23024, -0.63258, 2.13368)),
    (None, 11, (0.0, 0.0, 1.11569)),
    ("lowerback", 0, (0.0, 0.0, 0.0)),
    ("upperback", 13, (0.01961, 2.0545, -0.14112)),
    ("thorax", 14, (0.01021, 2.06436, -0.05921)),
    ("lowerneck", 15, (0.0, 0.0, 0.0)),
    ("upperneck", 16, (0.00713, 1.56711, 0.14968)),
    ("head", 17, (0.03429, 1.56041, -0.10006)),
    (None, 18, (0.01305, 1.6256, -0.05265)),
    ("lclavicle", 15, (0.0, 0.0, 0.0)),
    ("lhumerus", 20, (3.54205, 0.90436, -0.17364)),
    ("lradius", 21, (4.86513, 0.0, 0.0)),
    ("lwrist", 22, (3.35554, 0.0, 0.0)),
    ("lhand", 23, (0.0, 0.0, 0.0)),
    ("lfingers", 24, (0.66117, 0.0, 0.0)),
    (None, 25, (0.53306, 0.0, 0.0)),
    ("lthumb", 23, (0.0, 0.0, 0.0)),
    (None, 27, (0.5412, 0.0, 0.5412)),
    ("rclavicle", 15, (0.0, 0.0, 0.0)),
    ("rhumerus", 29, (-3.49802, 0.75994, -0.32616)),
    ("rradius", 30, (-5.02649, 0.0, 0.0)),
    ("rwrist", 31, (-3.36431, 0.0, 0.0)),
    ("rhand", 32, (0.0, 0.0, 0.0)),
    ("rfingers", 33, (-0.73041, 0.0, 0.0)),
    (None, 34, (-0.58887, 0.0, 0.0)),
    ("rthumb", 32, (0.0, 0.0, 0.0)),
    (None, 36, (-0.59786, 0.0, 0.59786)),
)
JOINT_NODES = tuple(i for i, (name, _, _) in enumerate(SKELETON) if name is not None)  # 31 nodes with channels


def read_expmap_csv(text: str) -> np.ndarray:
    """The CSV's frames without the T-pose line 0: ``(T, 117)``, root position then 38 exponential maps."""
    rows = [[float(v) for v in line.split(",")] for line in text.splitlines() if line.strip()]
    frames = np.asarray(rows, dtype=np.float64)
    if frames.ndim != 2 or frames.shape[1] != VALUES_PER_ROW:
        raise ValueError(f"expected {VALUES_PER_ROW} comma-separated values per line, got shape {frames.shape}")
    if len(frames) < 2:
        raise ValueError("expected the T-pose line and at least one frame")
    return frames[1:]


def local_rotations(expmap_rad: np.ndarray) -> np.ndarray:
    """Rodrigues(r)ᵀ per frame, the joint's local rotation in column form: ``(T, 3)`` -> ``(T, 3, 3)``.

    Rodrigues as the repository's ``data_utils.expmap2rotmat`` computes it (same operations, so the same bits).
    """
    theta = np.linalg.norm(expmap_rad, axis=1)
    axis = expmap_rad / np.maximum(theta, np.finfo(np.float32).eps)[:, None]
    skew = np.zeros((len(expmap_rad), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    skew = skew - skew.transpose(0, 2, 1)
    rodrigues = np.eye(3) + np.sin(theta)[:, None, None] * skew + (1 - np.cos(theta))[:, None, None] * (skew @ skew)
    return rodrigues.transpose(0, 2, 1)


def euler_zxy_deg(R: np.ndarray) -> np.ndarray:
    """Intrinsic ZXY angles of R = Rz(z)·Rx(x)·Ry(y), unwrapped along time: ``(T, 3, 3)`` -> ``(T, 3)`` (z, x, y)."""
    z = np.arctan2(-R[:, 0, 1], R[:, 1, 1])
    x = np.arcsin(np.clip(R[:, 2, 1], -1.0, 1.0))
    y = np.arctan2(-R[:, 2, 0], R[:, 2, 2])
    return np.degrees(np.unwrap(np.stack([z, x, y], axis=1), axis=0))


def motion_channels(frames: np.ndarray) -> np.ndarray:
    """BVH channel values: ``(T, 117)`` CSV frames -> ``(T, 96)`` (root position in m, then 31 × ZXY in degrees)."""
    n_frames = len(frames)
    expmaps = frames[:, 3:].reshape(n_frames, len(SKELETON), 3)
    columns = [frames[:, :3] * METRES_PER_ASF_UNIT]
    columns += [euler_zxy_deg(local_rotations(expmaps[:, node])) for node in JOINT_NODES]
    return np.concatenate(columns, axis=1)


def _number(value: float) -> str:
    text = f"{value:.6f}"
    return "0.000000" if text == "-0.000000" else text


def hierarchy_lines() -> list[str]:
    """The HIERARCHY section, tab-indented, the same in every file."""
    lines = ["HIERARCHY"]
    open_depths: list[int] = []  # depth of each node whose block is still open

    def close_to(depth: int) -> None:
        while open_depths and open_depths[-1] >= depth:
            lines.append("\t" * open_depths.pop() + "}")

    depths: list[int] = []
    for name, parent, offset in SKELETON:
        depth = 0 if parent < 0 else depths[parent] + 1
        depths.append(depth)
        close_to(depth)
        tabs = "\t" * depth
        head = "ROOT root" if parent < 0 else f"JOINT {name}" if name else "End Site"
        lines += [tabs + head, tabs + "{"]
        lines.append(tabs + "\tOFFSET " + " ".join(f"{v * METRES_PER_ASF_UNIT:.6f}" for v in offset))
        if parent < 0:
            lines.append(tabs + "\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation")
        elif name:
            lines.append(tabs + "\tCHANNELS 3 Zrotation Xrotation Yrotation")
        open_depths.append(depth)
    close_to(0)
    return lines


def csv_to_bvh(text: str) -> str:
    """The whole conversion: li2018 CSV text -> BVH text (``\\n`` line ends, a final newline)."""
    channels = motion_channels(read_expmap_csv(text))
    lines = hierarchy_lines() + ["MOTION", f"Frames: {len(channels)}", f"Frame Time: {FRAME_TIME_S}"]
    lines += [" ".join(map(_number, row)) for row in channels]
    return "\n".join(lines) + "\n"
