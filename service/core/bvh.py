"""BVH reader and writer: hierarchy, channels and motion frames, exactly as written in the file.

No unit or axis conversion happens here (see ``service.core.kinematics``). Every joint's CHANNELS
line is honoured: channel order differs between sources (``../shared/data/README.md``).
"""

from __future__ import annotations

import gzip
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np


class BvhFormatError(ValueError):
    """The file is not valid BVH; the message says what was expected and what was found."""


@dataclass(frozen=True)
class BvhJoint:
    name: str
    parent: int  # -1 for the root
    offset: np.ndarray  # (3,) in file units
    channels: tuple[str, ...]  # e.g. ("Xposition", ..., "Zrotation", "Xrotation", "Yrotation")
    channel_start: int  # column of the first channel in the motion table


@dataclass(frozen=True)
class Bvh:
    joints: tuple[BvhJoint, ...]  # depth-first order: parents precede children
    end_sites: dict[int, np.ndarray]  # joint index -> end-site offset (3,)
    frame_time_s: float
    motion: np.ndarray  # (T, n_channels) in file units (degrees for rotations)

    @property
    def sample_rate_hz(self) -> float:
        return 1.0 / self.frame_time_s

    def joint_index(self, name: str) -> int:
        for i, joint in enumerate(self.joints):
            if joint.name == name:
                return i
        raise KeyError(f"joint {name!r} not in BVH; joints are {[j.name for j in self.joints]}")


# what opening a corrupt gzip or a file that is not text raises: a format error of that file
UNREADABLE = (EOFError, zlib.error, gzip.BadGzipFile, UnicodeDecodeError)


def _unreadable(path: Path, exc: Exception) -> BvhFormatError:
    return BvhFormatError(f"{path}: not a readable BVH file{' (gzip)' if path.suffix == '.gz' else ''}: {exc}")


def read_bvh(path: str | Path) -> Bvh:
    """Parse a BVH file, plain or gzipped (``.bvh.gz``)."""
    path = Path(path)
    try:
        text = gzip.open(path, "rt").read() if path.suffix == ".gz" else path.read_text()
    except UNREADABLE as exc:
        raise _unreadable(path, exc) from None
    tokens = text.split()
    return _parse(tokens, str(path))


def read_bvh_header(path: str | Path) -> tuple[Bvh, int]:
    """A BVH file's skeleton and frame time alone (no frames read: ``motion`` has no rows), plain or gzipped, and
    the number of frames its header declares."""
    path = Path(path)
    header = []
    try:
        with gzip.open(path, "rt") if path.suffix == ".gz" else path.open() as f:
            for line in f:
                header.append(line)
                if line.strip().startswith("Frame Time:"):
                    break
    except UNREADABLE as exc:
        raise _unreadable(path, exc) from None
    tokens = "".join(header).split()
    if "MOTION" not in tokens:
        raise BvhFormatError(f"{path}: expected 'MOTION' after the HIERARCHY, found the end of the file")
    k = tokens.index("MOTION")
    if k + 6 > len(tokens) or tokens[k + 1] != "Frames:":
        raise BvhFormatError(f"{path}: expected 'Frames: N' and 'Frame Time: s' after 'MOTION'")
    frames = _number(tokens[k + 2], int, "the frame count after 'Frames:'", str(path))
    tokens[k + 2] = "0"  # the header alone: no values follow
    return _parse(tokens, str(path)), frames


def _expect(tokens: list[str], i: int, word: str, where: str) -> int:
    if i >= len(tokens) or tokens[i] != word:
        found = tokens[i] if i < len(tokens) else "end of file"
        raise BvhFormatError(f"{where}: expected {word!r} at token {i}, found {found!r}")
    return i + 1


def _number(token: str, kind: type, what: str, where: str) -> int | float:
    try:
        return kind(token)
    except ValueError:
        raise BvhFormatError(f"{where}: expected {what}, found {token[:40]!r}") from None


def _parse(tokens: list[str], where: str) -> Bvh:
    i = _expect(tokens, 0, "HIERARCHY", where)
    joints: list[BvhJoint] = []
    end_sites: dict[int, np.ndarray] = {}
    stack: list[int] = []
    n_channels = 0
    while tokens[i] != "MOTION":
        word = tokens[i]
        if word in ("ROOT", "JOINT"):
            name = tokens[i + 1]
            i = _expect(tokens, i + 2, "{", where)
            i = _expect(tokens, i, "OFFSET", where)
            offset = np.array([_number(t, float, f"joint {name}'s OFFSET x y z", where) for t in tokens[i : i + 3]])
            i = _expect(tokens, i + 3, "CHANNELS", where)
            count = _number(tokens[i], int, f"joint {name}'s channel count", where)
            channels = tuple(tokens[i + 1 : i + 1 + count])
            i += 1 + count
            parent = stack[-1] if stack else -1
            joints.append(BvhJoint(name, parent, offset, channels, n_channels))
            n_channels += count
            stack.append(len(joints) - 1)
        elif word == "End":
            i = _expect(tokens, i + 2, "{", where)
            i = _expect(tokens, i, "OFFSET", where)
            end_sites[stack[-1]] = np.array(
                [_number(t, float, "an End Site OFFSET x y z", where) for t in tokens[i : i + 3]]
            )
            i = _expect(tokens, i + 3, "}", where)
        elif word == "}":
            stack.pop()
            i += 1
        else:
            raise BvhFormatError(f"{where}: unexpected token {word!r} in HIERARCHY at token {i}")
    i = _expect(tokens, i + 1, "Frames:", where)
    n_frames = _number(tokens[i], int, "the frame count after 'Frames:'", where)
    i = _expect(tokens, i + 1, "Frame", where)
    i = _expect(tokens, i, "Time:", where)
    frame_time_s = _number(tokens[i], float, "the seconds per frame after 'Frame Time:'", where)
    if not np.isfinite(frame_time_s) or frame_time_s <= 0:
        raise BvhFormatError(f"{where}: expected a positive 'Frame Time:' in seconds, found {tokens[i]!r}")
    try:
        values = np.array(tokens[i + 1 :], dtype=np.float64)
    except ValueError:
        for t in tokens[i + 1 :]:  # the first that is none, named
            _number(t, float, "numbers in the MOTION table", where)
        raise
    if not np.isfinite(values).all():
        k = int(np.flatnonzero(~np.isfinite(values))[0])
        row = k // n_channels if n_channels else 0
        raise BvhFormatError(f"{where}: frame {row} has a value that is not finite ({values[k]}); every value must be")
    if values.size != n_frames * n_channels:
        raise BvhFormatError(
            f"{where}: expected {n_frames} frames x {n_channels} channels = {n_frames * n_channels} values, "
            f"found {values.size}"
        )
    return Bvh(tuple(joints), end_sites, frame_time_s, values.reshape(n_frames, n_channels))


ROOT_CHANNELS = ("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation")
JOINT_CHANNELS = ("Zrotation", "Yrotation", "Xrotation")


def euler_zyx_deg(R: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` → intrinsic Z-Y-X Euler angles ``(..., 3)`` in degrees (z, y, x), so that
    R = Rz(z) Ry(y) Rx(x), as BVH's "Zrotation Yrotation Xrotation" channels read. Where y is ±90° (gimbal lock)
    only z ∓ x is defined: x is 0 there."""
    sy = -np.clip(R[..., 2, 0], -1.0, 1.0)
    y = np.arcsin(sy)
    locked = np.abs(sy) > 1.0 - 1e-9
    z = np.where(locked, np.arctan2(-R[..., 0, 1], R[..., 1, 1]), np.arctan2(R[..., 1, 0], R[..., 0, 0]))
    x = np.where(locked, 0.0, np.arctan2(R[..., 2, 1], R[..., 2, 2]))
    return np.degrees(np.stack([z, y, x], axis=-1))


def rotations_bvh(
    names: Sequence[str],
    parents: Sequence[int],
    offsets: np.ndarray,
    R_world: np.ndarray,
    root_position: np.ndarray,
    frame_time_s: float,
    end_sites: dict[int, np.ndarray],
) -> Bvh:
    """A skeleton's joint orientations ``(T, J, 3, 3)`` in a BVH world as a clip: each joint's rotation relative to
    its parent as Z-Y-X Euler channels (the root's relative to the world, with position channels holding
    ``root_position``, ``(3,)`` or ``(T, 3)``), ``offsets`` ``(J, 3)`` in the parent's frame (the root's unused)."""
    T, J = R_world.shape[:2]
    parent = np.array([max(k, 0) for k in parents])  # the root's own row is replaced below
    R_local = np.einsum("tsji,tsjk->tsik", R_world[:, parent], R_world)
    R_local[:, 0] = R_world[:, 0]
    joints, start = [], 0
    for k, name in enumerate(names):
        channels = ROOT_CHANNELS if parents[k] < 0 else JOINT_CHANNELS
        joints.append(BvhJoint(name, parents[k], np.zeros(3) if k == 0 else np.asarray(offsets[k]), channels, start))
        start += len(channels)
    motion = np.concatenate([np.broadcast_to(root_position, (T, 3)), euler_zyx_deg(R_local).reshape(T, 3 * J)], 1)
    return Bvh(tuple(joints), end_sites, frame_time_s, motion)


def format_bvh(bvh: Bvh, decimals: int = 4) -> str:
    """The text of a BVH file: the hierarchy, then the motion table, ``decimals`` after the point. ``read_bvh`` of
    the text gives ``bvh`` back to that precision. The joints must be in the file's (depth-first) order with their
    channels in that order, as ``read_bvh`` gives them."""
    return (
        bvh_hierarchy_text(bvh, decimals)
        + f"MOTION\nFrames: {len(bvh.motion)}\nFrame Time: {bvh.frame_time_s:.8f}\n"
        + bvh_motion_text(bvh.motion, decimals)
    )


def bvh_motion_text(motion: np.ndarray, decimals: int = 4) -> str:
    """Rows of a BVH motion table ``(T, channels)``, one line per frame ("" for none)."""
    return "".join(_numbers(row, decimals) + "\n" for row in motion)


def _numbers(values: np.ndarray, decimals: int) -> str:
    return " ".join(f"{x:.{decimals}f}" for x in np.round(values, decimals) + 0.0)  # +0: no "-0.0"


def bvh_hierarchy_text(bvh: Bvh, decimals: int = 4) -> str:
    """The HIERARCHY part of a BVH file, through the root's closing brace (``format_bvh``'s checks)."""
    children: dict[int, list[int]] = {}
    for k, joint in enumerate(bvh.joints):
        children.setdefault(joint.parent, []).append(k)
    order: list[int] = []
    stack = list(reversed(children.get(-1, [])))
    while stack:
        k = stack.pop()
        order.append(k)
        stack.extend(reversed(children.get(k, [])))
    if children.get(-1, []) != [0] or order != list(range(len(bvh.joints))):
        raise ValueError("a BVH file has one root, the first joint, and the others in depth-first order")
    starts = np.cumsum([0] + [len(j.channels) for j in bvh.joints])
    if [j.channel_start for j in bvh.joints] != starts[:-1].tolist() or bvh.motion.shape[1] != starts[-1]:
        raise ValueError("each joint's channels must follow the previous joint's in the motion table")
    lines = ["HIERARCHY"]

    def joint_lines(k: int, depth: int) -> None:
        joint, pad = bvh.joints[k], "\t" * depth
        lines.append(f"{pad}{'ROOT' if joint.parent < 0 else 'JOINT'} {joint.name}")
        lines.append(pad + "{")
        lines.append(f"{pad}\tOFFSET {_numbers(joint.offset, decimals)}")
        lines.append(f"{pad}\tCHANNELS {len(joint.channels)} {' '.join(joint.channels)}")
        for child in children.get(k, []):
            joint_lines(child, depth + 1)
        if k in bvh.end_sites:
            end = _numbers(bvh.end_sites[k], decimals)
            lines.extend([f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\tOFFSET {end}", f"{pad}\t}}"])
        lines.append(pad + "}")

    joint_lines(0, 0)
    return "\n".join(lines) + "\n"
