"""The seven lower-body segment classes of Zimmermann et al. 2018 (§2.1), in its order (docs/conventions.md)."""

from __future__ import annotations

from collections.abc import Sequence

SEGMENTS: tuple[str, ...] = (
    "LeftFoot",
    "LeftLowerLeg",
    "LeftUpperLeg",
    "Pelvis",
    "RightUpperLeg",
    "RightLowerLeg",
    "RightFoot",
)

# Left/right mirror of each class index, for "accuracy ignoring left/right" (Zimmermann et al. 2018 §4.3.1).
MIRROR: tuple[int, ...] = (6, 5, 4, 3, 2, 1, 0)

# Side-free body part of each class: foot, lower leg, upper leg, pelvis.
BODY_PART: tuple[str, ...] = ("foot", "lower_leg", "upper_leg", "pelvis", "upper_leg", "lower_leg", "foot")


def segment_index(name: str) -> int:
    """Class index of a segment name; raises ``KeyError`` naming the valid names."""
    try:
        return SEGMENTS.index(name)
    except ValueError:
        raise KeyError(f"unknown segment {name!r}; expected one of {', '.join(SEGMENTS)}") from None


def segment_indices(names: Sequence[str] | None) -> list[int] | None:
    """Class indices of segment names (None stays None: nothing declared)."""
    return None if names is None else [segment_index(name) for name in names]


def segment_names(indices: Sequence[int] | None) -> list[str] | None:
    """Segment names of class indices, in class order (None stays None)."""
    return None if indices is None else [SEGMENTS[k] for k in sorted(indices)]
