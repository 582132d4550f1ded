"""Rate transitions against exact rational arithmetic.

Ticks are integers and the signals take integer values, so every expected value is computed
with ``fractions.Fraction`` and the transitions must match it exactly (or to the one rounding
of a final division)."""
from fractions import Fraction

import numpy as np
import pytest

from orchestration.plan import transitions as tr
from orchestration.run.algorithm import tick_base
from orchestration.scene.loading import scene_from_dict


def history_of(signal, step, n):
    h = tr.SampleHistory(step)
    for k in range(n):
        h.append(k * step, np.array([float(signal(k * step))]))
    return h


def linear(t):
    return 7 + 3 * t


def test_hold_takes_the_latest_sample_at_or_before_tau():
    h = history_of(linear, 4, 5)          # samples at 0, 4, 8, 12, 16
    for tau in range(0, 20):
        value, tick = tr.hold(h, tau)
        assert tick == (tau // 4) * 4
        assert value[0] == linear(tick)
    with pytest.raises(LookupError):
        tr.hold(h, -1)


def test_interpolate_is_exact_for_a_linear_signal_one_step_late():
    h = history_of(linear, 4, 6)
    for tau in range(4, 21):
        # the value at tau - H, exactly: weights k/4 are dyadic, values are integers
        assert tr.interpolate(h, tau)[0] == float(Fraction(linear(Fraction(tau - 4))))
    # before there is a sample to look back to, the first one is held
    assert tr.interpolate(h, 2)[0] == linear(0)


def test_extrapolate_is_exact_for_a_linear_signal_and_first_order_otherwise():
    h = history_of(linear, 4, 4)
    for tau in range(12, 16):
        assert tr.extrapolate(h, tau)[0] == linear(tau)
    quad = history_of(lambda t: t * t, 4, 4)     # 0, 16, 64, 144 at 0, 4, 8, 12
    # y(12) + (tau - 12) * (y(12) - y(8)) / 4
    for tau in range(12, 16):
        assert tr.extrapolate(quad, tau)[0] == 144 + (tau - 12) * (144 - 64) / 4
    single = history_of(linear, 4, 1)
    assert tr.extrapolate(single, 3)[0] == linear(0)


def reference_average(history: tr.SampleHistory, tau: int, window: int) -> np.ndarray:
    """The plain definition: the kept samples with tick in ``(tau - window, tau]``, summed in time
    order from a copy of the first, divided by their number."""
    inside = [v for t, v in zip(history.ticks, history.values) if tau - window < t <= tau]
    total = inside[0].copy()
    for value in inside[1:]:
        total += value
    total /= len(inside)
    return total


def average_of(samples, producer_step: int, window: int):
    """The Average transition fed with ``samples`` [(tick, array)], as the master feeds it."""
    transition = tr.REGISTRY["average"](producer_step, window)
    for tick, value in samples:
        transition.history.append(tick, value)
    return transition


def test_average_over_one_30hz_step_of_1khz_samples_counts_33_or_34():
    # ticks of 1/3000 s: haptic samples every 3 ticks, tissue steps of 100 ticks
    transition = average_of([(3 * k, np.array([float(k * k)])) for k in range(400)], 3, 100)
    counts = []
    for frame in range(1, 4):
        tau = 100 * frame
        inside = [k for k in range(400) if tau - 100 < 3 * k <= tau]
        counts.append(len(inside))
        expected = Fraction(sum(k * k for k in inside), len(inside))
        assert transition.value(tau)[0][0] == float(expected)
    assert counts == [33, 33, 34]


def test_average_of_vectors_is_componentwise():
    transition = average_of([(k, np.array([k, -2.0 * k, 1.0])) for k in range(10)], 1, 4)
    np.testing.assert_array_equal(transition.value(8)[0], [6.5, -13.0, 1.0])  # samples 5..8


def test_the_running_window_sums_give_the_plain_average_bit_for_bit():
    """The Average transition sums as samples arrive (WindowSums); its means must be the plain
    definition's, bitwise, for 1 kHz vectors into 30 Hz windows (33 or 34 samples), with the
    master's pruning in between and each window read at its end, as a jacobi and a gauss-seidel
    consumer do."""
    rng = np.random.default_rng(7)
    reference = tr.SampleHistory(3)
    transition = tr.REGISTRY["average"](3, 100)
    sums = transition.history
    assert isinstance(sums, tr.WindowSums) and not sums.keeps_values
    checked = 0
    for k in range(1000):
        sample = rng.normal(scale=rng.uniform(1e-3, 1e3), size=8064)
        reference.append(3 * k, sample.copy())
        sums.append(3 * k, sample)
        sample[:] = np.nan  # the host's buffer is overwritten by its next step: nothing may keep it
        tau = (3 * k // 100) * 100  # the latest window every sample of which has arrived
        if tau > 0 and 3 * k - 3 < tau <= 3 * k:
            expected = reference_average(reference, tau, 100)
            got = transition.value(tau)[0]
            assert got.tobytes() == expected.tobytes()
            assert transition.value(tau)[0].tobytes() == expected.tobytes()  # asking again changes nothing
            checked += 1
        sums.prune(3 * k - 2 * 3 - 100)
        reference.prune(3 * k - 2 * 3 - 100)
    assert checked == 29
    with pytest.raises(ValueError, match="not the end of a window"):
        transition.value(150)
    with pytest.raises(LookupError, match="no sample"):
        transition.value(100)  # pruned long ago
    with pytest.raises(ValueError, match="time order"):
        sums.append(3 * 999, np.zeros(8064))


def test_prune_keeps_what_consumers_can_still_ask_for():
    h = history_of(linear, 3, 50)
    h.prune(100)
    assert h.ticks[0] <= 100 < h.ticks[1] + 3
    assert tr.hold(h, 100)[1] == 99
    h.prune(10 ** 9)
    assert len(h.ticks) == 2


def test_samples_must_arrive_in_order():
    h = history_of(linear, 3, 3)
    with pytest.raises(ValueError, match="time order"):
        h.append(3, np.zeros(1))


def test_tick_base_is_the_lcm_of_the_step_denominators(tmp_path):
    scene = scene_from_dict({
        "scene": {"duration": 2.0},
        "source": {"a": {"kind": "piecewise_linear", "times": [0.0, 1.0], "outputs": {"y": [0.0, 1.0]}}},
        "block": {"d": {"kind": "device_plant", "step": "1/30"},
                  "e": {"kind": "device_plant", "step": 0.001}},
    }, tmp_path)
    base = tick_base(scene)
    assert base == 3000
    assert scene.components["d"].step * base == 100 and scene.components["e"].step * base == 3


def test_extend_is_append_one_at_a_time():
    """The compiled loop hands a stretch's samples over at once: the same history as appending each."""
    from orchestration.plan.transitions import SampleHistory

    one, many = SampleHistory(3), SampleHistory(3)
    one.append(3, np.array([1.0]))
    many.append(3, np.array([1.0]))
    samples = np.arange(8.0).reshape(4, 2)
    for tick, value in zip([6, 9, 12, 15], samples):
        one.append(tick, value)
    many.extend([6, 9, 12, 15], samples)
    assert list(one.ticks) == list(many.ticks) and one.count == many.count == 5
    assert all(a.tobytes() == b.tobytes() for a, b in zip(one.values, many.values))
    with pytest.raises(ValueError, match="time order"):
        many.extend([15, 18], samples[:2])


def naive_prune(ticks: list[int], keep_from: int) -> list[int]:
    """The definition: drop the oldest sample while it and the next are both older than the
    consumers can ask for, keeping the latest two."""
    ticks = list(ticks)
    while len(ticks) > 2 and ticks[1] <= keep_from and ticks[0] < keep_from:
        ticks.pop(0)
    return ticks


def test_prune_drops_what_the_definition_drops():
    rng = np.random.default_rng(3)
    for _ in range(300):
        ticks = np.cumsum(rng.integers(1, 5, size=rng.integers(0, 12))).tolist()
        h = tr.SampleHistory(1)
        h.extend(ticks, [np.array([float(t)]) for t in ticks])
        keep_from = int(rng.integers(-2, (ticks[-1] if ticks else 0) + 3))
        h.prune(keep_from)
        assert list(h.ticks) == naive_prune(ticks, keep_from)
        assert [v[0] for v in h.values] == [float(t) for t in h.ticks]


def test_summed_samples_counted_at_once_are_the_samples_appended_one_at_a_time():
    """The compiled loop adds a stretch's samples into the window sums itself and counts them in one
    call: the same sums, counts and means as appending each sample, whether a window opened before
    the stretch or inside it."""
    rng = np.random.default_rng(11)
    one, many = tr.WindowSums(3, 100), tr.WindowSums(3, 100)
    tick = 0
    for stretch in range(40):
        ticks = [tick + 3 * (i + 1) for i in range(int(rng.integers(1, 70)))]
        tick = ticks[-1]
        opened = {}
        for t in ticks:
            sample = rng.normal(size=5)
            one.append(t, sample)
            end = -(-t // 100) * 100
            total = many.window_sum(end)
            if total is None and end not in opened:
                opened[end] = sample.copy()  # the window's first sample: its sum
            else:
                (opened[end] if total is None else total)[:] += sample
        many.extend_summed(ticks, opened)
        assert one.count == many.count and list(one.ticks) == list(many.ticks)
        assert one._sums.keys() == many._sums.keys()
        for end, (total, count) in one._sums.items():
            assert many._sums[end][1] == count and many._sums[end][0].tobytes() == total.tobytes()
        one.prune(tick - 300)
        many.prune(tick - 300)
    with pytest.raises(ValueError, match="time order"):
        many.extend_summed([tick], {})


def test_extend_with_a_prune_keeps_what_extend_then_prune_keeps():
    rng = np.random.default_rng(5)
    for _ in range(300):
        ticks = np.cumsum(rng.integers(1, 5, size=rng.integers(1, 20))).tolist()
        split = int(rng.integers(0, len(ticks)))
        keep_from = int(rng.integers(-2, ticks[-1] + 3))
        values = np.array(ticks, dtype=float)[:, None]
        one, many = tr.SampleHistory(1), tr.SampleHistory(1)
        for h in (one, many):
            h.extend(ticks[:split], values[:split])
        one.extend(ticks[split:], values[split:])
        one.prune(keep_from)
        tape = values.copy()  # as the compiled loop's tape: overwritten after the call
        many.extend(ticks[split:], tape[split:], keep_from, copy=True)
        tape[:] = -1.0
        assert list(many.ticks) == list(one.ticks) == naive_prune(ticks, keep_from)
        assert [v[0] for v in many.values] == [float(t) for t in many.ticks] and many.count == one.count
