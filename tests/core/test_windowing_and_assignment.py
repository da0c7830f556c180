import itertools

import numpy as np
import pytest

from service.core.assignment import (
    SWING,
    SWING_PAIR_TYPES,
    MomentAssembler,
    allowed_segments,
    is_moving,
    joint_assignment,
    pelvis_lateral,
    session_assignment,
    sway_log_likelihood,
    sway_table,
    sway_z,
    swing_log_likelihood,
    swing_pair_type,
    swing_per_moment,
    swing_z,
    window_joint_assignment,
)
from service.core.resample import resample_uniform
from service.core.units import UnitError, to_contract_units
from service.core.windowing import sliding_windows, window_starts


def test_sliding_windows_equal_a_loop() -> None:
    x = np.arange(300 * 6, dtype=np.float32).reshape(300, 6)
    w = sliding_windows(x)
    starts = window_starts(300)
    assert w.shape == (len(starts), 128, 6)
    for k, s in enumerate(starts):
        np.testing.assert_array_equal(w[k], x[s : s + 128])
    assert sliding_windows(x[:100]).shape == (0, 128, 6)


def test_units_and_unknown_unit() -> None:
    out = to_contract_units(np.array([[1.0, 0, 0, 180.0, 0, 0]]), "g", "deg/s")
    np.testing.assert_allclose(out, [[9.80665, 0, 0, np.pi, 0, 0]])
    with pytest.raises(UnitError, match="accelerometer unit"):
        to_contract_units(np.zeros((1, 6)), "ft/s^2", "rad/s")


def test_resampling_keeps_a_slow_sine_and_length() -> None:
    t = np.arange(0, 4, 1 / 100.0)
    x = np.sin(2 * np.pi * 1.0 * t)[:, None]
    y = resample_uniform(x, 100.0, 60.0)
    assert len(y) == 240  # 4 s at 60 Hz
    t60 = np.arange(len(y)) / 60.0
    np.testing.assert_allclose(y[20:-20, 0], np.sin(2 * np.pi * t60[20:-20]), atol=0.02)


def test_joint_assignment_resolves_a_conflict() -> None:
    # Both sensors prefer class 0 per window; the second prefers it less, so it takes class 1.
    a = np.log(np.array([[0.9, 0.1], [0.8, 0.2]]))
    b = np.log(np.array([[0.6, 0.4], [0.6, 0.4]]))
    joint = joint_assignment([a, b])
    assert joint.segment.tolist() == [0, 1]
    assert joint_assignment([a, b], allow_shared=True).segment.tolist() == [0, 0]


def test_more_sensors_than_segments_leaves_the_weakest_unassigned() -> None:
    lp = [np.log(np.array([[p, 1 - p]])) for p in (0.9, 0.2, 0.6)]
    assert joint_assignment(lp).segment.tolist() == [0, 1, -1]


def test_window_joint_assignment_decides_each_moment_on_its_own() -> None:
    # Moment 0: both sensors prefer class 0, the second less, so it takes class 1. Moment 1: the first sensor's
    # window is still, so the second takes its own best class 0. Moment 2 exists for the second sensor only.
    a = np.log(np.array([[0.9, 0.1], [0.9, 0.1]]))
    b = np.log(np.array([[0.6, 0.4], [0.6, 0.4], [0.3, 0.7]]))
    moving = [np.array([True, False]), np.array([True, True, True])]
    out = window_joint_assignment([a, b], moving)
    assert [o.tolist() for o in out] == [[0, -1], [1, 0, 1]]
    # Three moving windows, two classes: the weakest window at that moment is left unassigned.
    lp = [np.log(np.array([[p, 1 - p]])) for p in (0.9, 0.2, 0.6)]
    assert [o.tolist() for o in window_joint_assignment(lp, [np.array([True])] * 3)] == [[0], [1], [-1]]
    assert window_joint_assignment([], []) == []


def test_declared_worn_segments_restrict_every_answer() -> None:
    # Two foot sensors (classes 0 and 6 of seven). Both favour shank classes; declared as feet, the one with the
    # stronger left-foot evidence takes class 0 and the other class 6, per recording and per moment.
    probs = np.full((2, 2, 7), 0.01)
    probs[0, :, [0, 1]] = [[0.30, 0.30], [0.64, 0.64]]  # sensor 0: LeftFoot 0.30, LeftLowerLeg 0.64
    probs[1, :, [0, 5, 6]] = [[0.20, 0.20], [0.64, 0.64], [0.10, 0.10]]  # sensor 1: RightLowerLeg 0.64
    lp = list(np.log(probs))
    free = joint_assignment(lp)
    assert free.segment.tolist() == [1, 5]
    feet = joint_assignment(lp, worn=[6, 0])
    assert feet.segment.tolist() == [0, 6]
    # Margins and confidences are over the worn segments: 2 × (log 0.30 − log 0.01) and 2 × (log 0.10 − log 0.20).
    np.testing.assert_allclose(feet.margin, [2 * np.log(30.0), 2 * np.log(0.5)])
    np.testing.assert_allclose(feet.confidence, [30**2 / (30**2 + 1), 1 / (1 + 2**2)])
    assert np.isneginf(feet.evidence[:, [1, 2, 3, 4, 5]]).all()
    moving = [np.array([True, False]), np.array([True, True])]
    assert [o.tolist() for o in window_joint_assignment(lp, moving, worn=[0, 6])] == [[0, -1], [6, 0]]
    assert [o.tolist() for o in window_joint_assignment(lp, moving, allow_shared=True, worn=[0, 6])] == [
        [0, -1],
        [0, 0],
    ]
    # One declared segment, two sensors: the weaker is left over.
    assert joint_assignment(lp, worn=[0]).segment.tolist() == [0, -1]
    live = MomentAssembler(2, worn=[0, 6])
    live.add(0, 1.0, lp[0][0], True)
    live.add(1, 1.0, lp[1][0], True)
    assert live.ready() == [(1.0, {0: 0, 1: 6})]
    for bad in ([], [0, 0], [7], [-1]):
        with pytest.raises(ValueError, match="distinct class indices"):
            joint_assignment(lp, worn=bad)


def test_per_sensor_candidates_fill_every_sensor_the_declaration_allows() -> None:
    # Sensor 0 is declared the pelvis; sensors 1 and 2 are "a foot" each (side unknown). Sensor 1 favours the left
    # foot more strongly than sensor 2 does, sensor 2 favours a shank overall; sensor 0 favours the left thigh.
    probs = np.full((3, 1, 7), 0.01)
    probs[0, 0, [2, 3]] = [0.80, 0.14]
    probs[1, 0, [0, 6]] = [0.90, 0.04]
    probs[2, 0, [0, 5, 6]] = [0.50, 0.39, 0.05]
    lp = list(np.log(probs))
    feet = [0, 6]
    answer = joint_assignment(lp, candidates=[[3], feet, feet])
    assert answer.segment.tolist() == [3, 0, 6]
    assert np.isinf(answer.margin[0]) and answer.confidence[0] == 1.0  # one candidate: no other to lead
    np.testing.assert_allclose(answer.margin[1:], [np.log(0.90 / 0.04), np.log(0.05 / 0.50)])
    moving = [np.array([True])] * 3
    assert [o.tolist() for o in window_joint_assignment(lp, moving, candidates=[[3], feet, feet])] == [[3], [0], [6]]
    # Sensor 2 may only be the left foot, sensor 1 either foot: both get one, though sensor 1 prefers the left.
    assert joint_assignment(lp, candidates=[None, feet, [0]]).segment.tolist() == [2, 6, 0]
    # Two sensors that may only be the left foot: the weaker is left over; the others keep their answers.
    assert joint_assignment(lp, candidates=[None, [0], [0]]).segment.tolist() == [2, 0, -1]
    # worn and candidates together: the intersection.
    assert allowed_segments(2, 7, worn=[0, 3, 6], candidates=[feet, None]).nonzero()[1].tolist() == [0, 6, 0, 3, 6]
    with pytest.raises(ValueError, match="none of their candidate segments is among the worn ones"):
        joint_assignment(lp, worn=[0, 6], candidates=[[3], None, None])
    with pytest.raises(ValueError, match="one entry per sensor"):
        joint_assignment(lp, candidates=[feet])
    with pytest.raises(ValueError, match="distinct class indices"):
        MomentAssembler(3, candidates=[[0, 0], None, None])
    live = MomentAssembler(3, candidates=[[3], feet, feet])
    for s in range(3):
        live.add(s, 1.0, lp[s][0], True)
    assert live.ready() == [(1.0, {0: 3, 1: 0, 2: 6})]


def test_live_moments_wait_for_every_sensor_and_give_the_batch_answer() -> None:
    strong, weak = np.log(np.array([0.9, 0.1])), np.log(np.array([0.6, 0.4]))
    live = MomentAssembler(2, max_open=2)
    live.add(0, 2.1166667, strong, True)
    live.add(0, 2.3833333, strong, True)
    assert live.ready() == []  # sensor 1 has sent nothing yet
    live.add(1, 2.1166667, weak, True)
    assert live.ready() == [(2.116667, {0: 0, 1: 1})]  # one-to-one at the moment both reached
    live.add(0, 2.65, weak, False)
    live.add(0, 2.9166667, strong, True)
    live.add(0, 3.1833333, strong, True)
    # sensor 1 stalls: beyond two open moments the oldest are answered without it
    assert live.ready() == [(2.383333, {0: 0}), (2.65, {0: -1})]
    assert live.flush() == [(2.916667, {0: 0}), (3.183333, {0: 0})] and live.flush() == []
    shared = MomentAssembler(2, allow_shared=True)
    shared.add(0, 1.0, strong, True)
    shared.add(1, 1.0, weak, True)
    assert shared.ready() == [(1.0, {0: 0, 1: 0})]


def test_is_moving() -> None:
    still = np.zeros((1, 128, 6))
    spinning = still.copy()
    spinning[..., 3] = 2.0
    assert is_moving(np.concatenate([still, spinning])).tolist() == [False, True]


def _walking_norms(rng: np.random.Generator) -> np.ndarray:
    """Gyroscope norms of seven sensors (class order) over one window of a made-up walk: the left leg's three swing
    together, the right leg's in the other half of the stride, the pelvis twice per stride."""
    t = np.arange(128) / 60.0
    phase = 2 * np.pi * t / 1.1
    left, right, pelvis = 2 + np.sin(phase), 2 - np.sin(phase), 1 + 0.3 * np.sin(2 * phase)
    norms = np.stack([left, left, left, pelvis, right, right, right])
    return norms + 0.3 * rng.standard_normal(norms.shape)


def test_swing_pair_types_cover_every_pair_once_and_symmetrically() -> None:
    seen = {swing_pair_type(a, b) for a in range(7) for b in range(7) if a != b}
    assert seen == set(range(len(SWING_PAIR_TYPES))) and set(SWING) == set(SWING_PAIR_TYPES)
    assert all(swing_pair_type(a, b) == swing_pair_type(b, a) for a in range(7) for b in range(7) if a != b)
    assert SWING_PAIR_TYPES[swing_pair_type(0, 2)] == "same_leg-foot-upper_leg"  # left foot, left thigh
    assert SWING_PAIR_TYPES[swing_pair_type(0, 4)] == "both_legs-foot-upper_leg"  # left foot, right thigh
    assert SWING_PAIR_TYPES[swing_pair_type(6, 5)] == "same_leg-foot-lower_leg"
    assert SWING_PAIR_TYPES[swing_pair_type(3, 1)] == "pelvis-lower_leg"
    z = swing_z(np.stack([np.sin(np.arange(128) / 9.0), -np.sin(np.arange(128) / 9.0), np.ones(128)]))
    assert z[0, 1] == pytest.approx(-3.0) and z[0, 2] == 0.0 and z[2, 2] == 0.0  # clipped; a flat norm reads 0


def test_sensors_that_swing_together_answer_a_leg_together() -> None:
    """A thigh whose own window leans to the wrong side: the one-to-one answer of the windows alone swaps the
    thighs; weighing how the sensors swing puts each thigh with its foot and shank."""
    rng = np.random.default_rng(0)
    probs = np.full((7, 7), 0.01)
    np.fill_diagonal(probs, 0.9)
    probs[2, [2, 4]] = [0.30, 0.60]  # the left thigh's window favours the right thigh
    probs[4, [2, 4]] = [0.40, 0.50]
    log_probs = [np.log(p / p.sum())[None] for p in probs]
    moving = [np.array([True])] * 7
    alone = window_joint_assignment(log_probs, moving)
    assert [int(a[0]) for a in alone] == [0, 1, 4, 3, 2, 5, 6]
    norms = [n[None] for n in _walking_norms(rng)]
    together = window_joint_assignment(log_probs, moving, gyro_norms=norms)
    assert [int(a[0]) for a in together] == list(range(7))
    assert [int(a[0]) for a in window_joint_assignment(log_probs, moving, gyro_norms=norms, swing_weight=0.0)] == [
        int(a[0]) for a in alone
    ]
    live = MomentAssembler(7)
    for s in range(7):
        live.add(s, 1.0, log_probs[s][0], True, norms[s][0])
    assert live.ready() == [(1.0, dict(enumerate(range(7))))]
    # Declarations still hold: with the left thigh declared the right one, the swing cannot move it back.
    declared = window_joint_assignment(log_probs, moving, candidates=[None, None, [4]] + [None] * 4, gyro_norms=norms)
    assert int(declared[2][0]) == 4


def test_the_pelvis_sway_puts_each_leg_sensor_on_its_side() -> None:
    """A pelvis sensor and one foot sensor per leg. The feet swing in turn; the pelvis sways left while the left
    foot swings. Both feet's windows lean to the wrong side, the left one more: the windows alone and how the sensors
    swing together swap them; the pelvis' sway (in its sensor's frame, here turned by a half turn about z from the
    pelvis frame, as the alignment would give it) puts each on its side. Weight 0, no table, or no pelvis among the
    sensors answers as before."""
    rng = np.random.default_rng(3)
    t = np.arange(128) / 60.0
    phase = 2 * np.pi * t / 1.1
    left, right = 2 + np.sin(phase), 2 - np.sin(phase)
    feet = np.stack([left, right]) + 0.2 * rng.standard_normal((2, 128))
    pelvis_norm = 1 + 0.3 * np.sin(2 * phase)
    window = np.zeros((128, 6))
    window[:, 2] = 9.81
    window[:, 1] = -0.8 * np.sin(phase)  # along the sensor's y, which is the pelvis' −y: the pelvis sways left
    q_pelvis_imu = np.array([0.0, 0.0, 0.0, 1.0])  # a half turn about z
    lateral = pelvis_lateral(window[None], q_pelvis_imu)[0]
    z = sway_z(lateral, feet)
    assert z[0] > 0.5 and z[1] < -0.5
    table = sway_table(
        {
            f"{side}{part}": (sign * 0.2, 0.3)
            for side, sign in (("Left", 1), ("Right", -1))
            for part in ("Foot", "LowerLeg", "UpperLeg")
        }
    )
    ll = sway_log_likelihood(z, table)
    assert ll[0, 0] > ll[0, 6] and ll[1, 6] > ll[1, 0] and (ll[:, 3] == 0).all()
    probs = np.full((3, 7), 0.01)
    probs[0, [0, 6]] = [0.40, 0.55]  # the left foot's window leans right
    probs[1, [0, 6]] = [0.50, 0.45]
    probs[2, 3] = 0.9
    log_probs = [np.log(p / p.sum())[None] for p in probs]
    moving = [np.array([True])] * 3
    norms = [feet[0][None], feet[1][None], pelvis_norm[None]]
    laterals = [np.zeros((1, 128)), np.zeros((1, 128)), lateral[None]]  # the feet's would not sway this way
    without = [int(a[0]) for a in window_joint_assignment(log_probs, moving, gyro_norms=norms)]
    assert without == [6, 0, 3]
    sway = {"laterals": laterals, "sway": table, "sway_weight": 0.25}
    swayed = window_joint_assignment(log_probs, moving, gyro_norms=norms, **sway)
    assert [int(a[0]) for a in swayed] == [0, 6, 3]
    zero = window_joint_assignment(log_probs, moving, gyro_norms=norms, **(sway | {"sway_weight": 0.0}))
    assert [int(a[0]) for a in zero] == without
    untabled = window_joint_assignment(log_probs, moving, gyro_norms=norms, laterals=laterals, sway_weight=0.25)
    assert [int(a[0]) for a in untabled] == without
    no_pelvis = window_joint_assignment(
        log_probs[:2], moving[:2], gyro_norms=norms[:2], laterals=laterals[:2], sway=table, sway_weight=0.25
    )
    assert [int(a[0]) for a in no_pelvis] == without[:2]
    unsettled = [laterals[0], laterals[1], np.full((1, 128), np.nan)]  # the pelvis sensor's frame not known yet
    assert [
        int(a[0])
        for a in window_joint_assignment(log_probs, moving, gyro_norms=norms, **(sway | {"laterals": unsettled}))
    ] == without


@pytest.mark.parametrize("n_sensors", [2, 3, 5])
def test_the_swing_answer_is_the_best_one_to_one_map(n_sensors: int) -> None:
    rng = np.random.default_rng(n_sensors)
    for _ in range(5):
        log_probs = np.log(rng.dirichlet(np.ones(7), size=n_sensors))
        norms = (
            rng.standard_normal((n_sensors, 128))
            + np.sin(np.arange(128) / 10.0) * rng.choice([-1, 1], n_sensors)[:, None]
        )
        allowed = rng.random((n_sensors, 7)) > 0.2
        allowed[np.arange(n_sensors), rng.permutation(7)[:n_sensors]] = True  # some one-to-one map is allowed
        pair_ll = swing_log_likelihood(norms)

        def score(m: tuple[int, ...], log_probs=log_probs, pair_ll=pair_ll) -> float:
            own = sum(log_probs[i, c] for i, c in enumerate(m))
            pairs = sum(
                pair_ll[i, j, swing_pair_type(m[i], m[j])] for i in range(n_sensors) for j in range(i + 1, n_sensors)
            )
            return own + 0.125 * pairs

        feasible = [
            m for m in itertools.permutations(range(7), n_sensors) if all(allowed[i, c] for i, c in enumerate(m))
        ]
        best = max(feasible, key=score)
        candidates = [np.flatnonzero(a).tolist() for a in allowed]
        got = window_joint_assignment(
            [lp[None] for lp in log_probs],
            [np.array([True])] * n_sensors,
            candidates=candidates,
            gyro_norms=[n[None] for n in norms],
            swing_weight=0.125,
        )
        assert score(tuple(int(g[0]) for g in got)) == pytest.approx(score(best), abs=1e-4)


def test_a_session_answer_weighs_how_its_sensors_swung_together() -> None:
    """Over a session the left thigh's own windows lean to the right thigh; the summed swing of its moments puts it
    with the foot and shank it swung with, and its margin is what that answer wins by, swing included. Weight 0
    answers as without. The live sum (``MomentAssembler.swing``) is the REST one (``swing_per_moment``)."""
    rng = np.random.default_rng(1)
    n = 12
    probs = np.full((7, 7), 0.01)
    np.fill_diagonal(probs, 0.9)
    probs[2, [2, 4]] = [0.30, 0.60]
    probs[4, [2, 4]] = [0.40, 0.50]
    log_probs = [np.repeat(np.log(p / p.sum())[None], n, axis=0) for p in probs]
    norms_by_moment = np.stack([_walking_norms(rng) for _ in range(n)])  # (n, 7, T)
    norms = [norms_by_moment[:, s] for s in range(7)]
    moving = [np.ones(n, bool)] * 7
    alone, _, _ = session_assignment(log_probs, moving)
    assert alone.segment.tolist() == [0, 1, 4, 3, 2, 5, 6]
    swung, _, _ = session_assignment(log_probs, moving, gyro_norms=norms)
    assert swung.segment.tolist() == list(range(7))
    assert (swung.margin > 0).all() and alone.margin[4] < 0  # alone, the constraint overrode a thigh
    unweighed, _, _ = session_assignment(log_probs, moving, gyro_norms=norms, swing_weight=0.0)
    assert unweighed.segment.tolist() == alone.segment.tolist()
    np.testing.assert_allclose(unweighed.margin, alone.margin)
    live = MomentAssembler(7)
    for t in range(n):
        for s in range(7):
            live.add(s, float(t), log_probs[s][t], True, norms[s][t])
    live.ready(), live.flush()
    np.testing.assert_allclose(live.swing, swing_per_moment(norms, moving).sum(axis=0), rtol=1e-5, atol=1e-4)
    # Sensors with fewer windows: the moments they all recorded.
    assert swing_per_moment([norms[0][:5], norms[1], norms[2][:7]], [np.ones(5, bool), *moving[1:3]]).shape == (
        5,
        3,
        3,
        12,
    )
    # A still window's pairs are not weighed.
    still = [np.ones(n, bool)] * 6 + [np.arange(n) >= 4]
    per_moment = swing_per_moment(norms, still)
    assert (per_moment[:4, 6] == 0).all() and (per_moment[:4, :, 6] == 0).all() and (per_moment[4:, 6, 5] != 0).all()


def test_a_calibration_answers_sessions_as_it_was_fitted() -> None:
    from service.core.assignment import SWING_WEIGHT, ConfidenceModel, session_swing_weight
    from service.core.manifest import ConfidenceSpec

    spec = ConfidenceSpec(
        features=["vote_share", "margin_per_window", "log_moving_windows"],
        coef=[1.0, 1.0, 1.0],
        intercept=0.0,
        threshold=0.9,
        min_moving_windows=8,
        fitted_on="test",
    )
    assert session_swing_weight(ConfidenceModel.from_spec(spec)) == 0.0  # fitted before the swing was weighed
    spec.swing_weight = 0.125
    assert session_swing_weight(ConfidenceModel.from_spec(spec)) == 0.125
    assert session_swing_weight(None) == SWING_WEIGHT
