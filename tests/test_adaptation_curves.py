"""vafn_sb3.common.adaptation_curves: mean ± 95 % Student-t CI over seeds of per-seed task means, and its figure."""

from __future__ import annotations

import numpy as np
import pytest

from vafn_sb3 import aggregate_adaptation, plot_adaptation

T_975_2DF = 4.302652729749464  # Student-t 97.5 % quantile, 2 degrees of freedom (3 seeds)


def row(method: str, seed: int, k: int, success: float, collision: float, ret: float) -> dict:
    return {"method": method, "seed": seed, "k": k, "success_rate": success, "collision_rate": collision,
            "return_mean": ret}


def hand_rows() -> list[dict]:
    """Reference ``ref`` (one seed, K = 0, one task), then ``a``: 3 seeds x K in (0, 5) x 2 tasks."""
    rows = [row("ref", 0, 0, 1.0, 0.0, 7.0)]
    for seed, successes, collisions in ((0, (1, 0), (1, 0)), (1, (1, 1), (0, 0)), (2, (0, 0), (0, 0))):
        for task in range(2):
            rows.append(row("a", seed, 0, successes[task], collisions[task], seed + 2 * task))  # task means 1, 2, 3
            rows.append(row("a", seed, 5, 1.0, 0.0, 10.0))
    return rows


def test_mean_over_seeds_of_task_means_with_a_t_interval_and_clipped_rates():
    curves = aggregate_adaptation(hand_rows())
    assert list(curves) == ["success_rate", "collision_rate", "return_mean"]
    assert list(curves["success_rate"]) == ["ref", "a"], "methods in order of first appearance"

    success = curves["success_rate"]["a"]
    assert success.k.tolist() == [0, 5] and success.n_seeds == 3 and success.n_tasks == 2
    # K = 0: seed means 0.5, 1, 0 -> mean 0.5, sample std 0.5, half width t * 0.5 / sqrt(3) = 1.2421 (clipped band).
    assert success.mean == pytest.approx([0.5, 1.0])
    assert success.half_width == pytest.approx([T_975_2DF * 0.5 / np.sqrt(3), 0.0])
    assert success.low == pytest.approx([0.0, 1.0]) and success.high == pytest.approx([1.0, 1.0])

    collision = curves["collision_rate"]["a"]
    # K = 0: seed means 0.5, 0, 0 -> mean 1/6, sample std sqrt(1/12), half width t / 6 = 0.7171; low clipped to 0.
    assert collision.mean == pytest.approx([1 / 6, 0.0])
    assert collision.half_width == pytest.approx([T_975_2DF / 6, 0.0])
    assert collision.low == pytest.approx([0.0, 0.0]) and collision.high == pytest.approx([1 / 6 + T_975_2DF / 6, 0.0])

    ret = curves["return_mean"]["a"]
    # K = 0: seed means 1, 2, 3 -> mean 2, sample std 1, half width t / sqrt(3) = 2.4841; a return is not clipped.
    assert ret.mean == pytest.approx([2.0, 10.0])
    assert ret.low == pytest.approx([2 - T_975_2DF / np.sqrt(3), 10.0])
    assert ret.high == pytest.approx([2 + T_975_2DF / np.sqrt(3), 10.0])

    reference = curves["return_mean"]["ref"]
    assert reference.k.tolist() == [0] and reference.n_seeds == 1 and reference.n_tasks == 1
    assert reference.mean == pytest.approx([7.0]) and reference.half_width == pytest.approx([0.0])
    assert reference.low == pytest.approx([7.0]) and reference.high == pytest.approx([7.0])


def test_group_column_and_missing_cells():
    rows = [{**r, "algo": r.pop("method")} for r in hand_rows()]
    assert list(aggregate_adaptation(rows, group="algo")["success_rate"]) == ["ref", "a"]
    incomplete = [r for r in hand_rows() if not (r["seed"] == 1 and r["k"] == 5)]
    with pytest.raises(ValueError, match=r"a: no rows for \(seed, K\) in \[\(1, 5\)\]"):
        aggregate_adaptation(incomplete)
    with pytest.raises(ValueError, match="no adaptation rows"):
        aggregate_adaptation([])


def test_plot_writes_a_png(tmp_path):
    path = plot_adaptation(aggregate_adaptation(hand_rows()), tmp_path / "fig" / "curves.png", "title",
                           references=("ref",))
    assert path == tmp_path / "fig" / "curves.png"
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 10_000


def test_zero_shot_panel_is_drawn_as_bars_with_their_intervals(tmp_path, monkeypatch):
    from matplotlib.axes import Axes

    bars = []
    draw = Axes.bar

    def record(self, x, height, **kwargs):
        bars.append((x, height, kwargs))
        return draw(self, x, height, **kwargs)

    monkeypatch.setattr(Axes, "bar", record)
    zero_shot = [r for r in hand_rows() if r["k"] == 0]
    plot_adaptation(aggregate_adaptation(zero_shot), tmp_path / "bars.png", references=("ref",))
    assert len(bars) == 3 * 2, "one bar per method and metric"
    (_, _, reference), (_, height, method) = bars[:2]  # the success-rate panel
    assert reference["hatch"] == "//" and reference["yerr"] is None                # the one-seed reference
    assert height == pytest.approx(0.5) and np.ravel(method["yerr"]) == pytest.approx([0.5, 0.5])  # clipped to [0, 1]
    bars.clear()
    plot_adaptation(aggregate_adaptation(hand_rows()), tmp_path / "curves.png", references=("ref",))
    assert not bars, "a panel over K stays a line plot"
