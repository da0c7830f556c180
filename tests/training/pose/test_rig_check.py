"""The rig check's hinge axis: a simulated elbow whose axis is turned about the upper arm's long axis."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from training.pose.rig_check import azimuth_elevation_deg, hinge_in_proximal


@pytest.mark.parametrize("turn_deg", [-25.0, 0.0, 11.0])
def test_the_hinge_axis_is_found_in_the_proximal_frame_whatever_the_upper_arm_does(turn_deg: float) -> None:
    rng = np.random.default_rng(1)
    t = np.linspace(0.0, 6.0, 600)
    upper = Rotation.from_rotvec(np.c_[0.3 * np.sin(t), 0.2 * np.cos(1.3 * t), 0.5 * np.sin(0.7 * t)])
    axis = Rotation.from_euler("z", turn_deg, degrees=True).apply([0.0, 1.0, 0.0])  # y turned about z
    flexion = np.radians(10 + 25 * (1 + np.sin(2 * np.pi * t)))  # 10-60° of elbow flexion
    carrying = Rotation.from_euler("x", 8, degrees=True)  # a constant carrying angle of the forearm's frame
    fore = upper * Rotation.from_rotvec(flexion[:, None] * axis) * carrying
    noise = Rotation.from_rotvec(rng.normal(0, np.radians(0.5), size=(len(t), 3)))
    found, motion = hinge_in_proximal(upper.as_matrix(), (fore * noise).as_matrix())
    azimuth, elevation = azimuth_elevation_deg(found)
    assert azimuth == pytest.approx(turn_deg, abs=1.0) and abs(elevation) < 1.0
    assert motion == pytest.approx(50.0, abs=3.0)
