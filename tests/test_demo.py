"""vafn-demo end to end: media -> MultimediaStream -> queue -> OnlineController -> labelled video and timeline."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("librosa")
pytest.importorskip("cv2")

from vafn_app import demo  # noqa: E402


class _Doubtful:
    """Delegates to the real generator but reports the inputs in ``doubtful`` (by code) as low-confidence readings."""

    def __init__(self, generator: Any, doubtful: str) -> None:
        self.generator = generator
        self.doubtful = doubtful

    def transcribe(self, **kwargs: Any) -> Any:
        result = self.generator.transcribe(**kwargs)
        if kwargs.get("code") == self.doubtful:
            return dataclasses.replace(result, confidence=0.2, low_confidence=True, warnings=("test: doubtful",))
        return result


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[demo.DemoResult, Path, list[demo.DemoInput]]:
    import torch
    from PIL import Image

    from vafn_media import InstructionGenerator
    from vafn_media.strips import render_strip

    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("demo")
    card = out / "card_13.png"
    Image.fromarray(render_strip((1, 3), np.random.default_rng(3))).save(card)
    inputs = demo.expand_inputs([("code", "2,1"), ("image", str(card)), ("code", "3")])
    generator = _Doubtful(InstructionGenerator.load(warm=False), doubtful="3")
    result = demo.run_demo(inputs, out, generator=generator, interval=20, max_steps=400, width=160, height=120,
                           frame_skip=4, video="gif", progress=False)
    return result, out, inputs


def test_demo_executes_instructions_in_order_and_reports_latency(demo_run: Any) -> None:
    result, out, _ = demo_run
    code, image, doubtful = result.outcomes
    assert (code.instruction, image.instruction) == ("2,1", "1,3")
    assert code.status == "completed" and image.status == "completed", [o.message for o in result.outcomes]
    assert code.start_step < image.start_step, "instructions run in arrival order"
    for outcome in (code, image):
        assert outcome.end_step > outcome.start_step >= outcome.arrival_step >= outcome.submit_step >= 0
        assert 0 <= outcome.dequeue_to_first_action_s <= outcome.arrival_to_first_action_s < 5.0
        assert outcome.completion_wall_s > outcome.submit_to_first_action_s > 0
    assert doubtful.status == "rejected" and not doubtful.executed and "low confidence" in doubtful.message
    assert "REJECTED (low confidence, not executed)" in demo.format_outcome(doubtful, 48.0)
    assert not result.all_succeeded
    rows = (out / "outcomes.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[0].startswith("index,kind,label,status")
    assert result.timeline.stat().st_size > 10_000


def test_demo_video_frames_carry_the_overlay(demo_run: Any) -> None:
    import gymnasium as gym
    from PIL import Image

    import vafn_gym  # noqa: F401

    result, _, _ = demo_run
    assert result.video is not None and result.video.suffix == ".gif"
    with Image.open(result.video) as gif:
        assert gif.n_frames == result.frames > 10
        gif.seek(0)
        labelled = np.asarray(gif.convert("RGB")).astype(float)
    env = gym.make(demo.ENV_ID, arrivals=None, render_mode="rgb_array", render_width=160, render_height=120)
    env.reset(seed=0)
    raw = env.render().astype(float)
    env.close()
    assert labelled.shape == raw.shape
    # The first frame is 4 steps in: the arms have barely moved, but the banners darken the top and bottom rows.
    for rows in (slice(0, 8), slice(-6, None)):
        assert raw[rows].mean() - labelled[rows].mean() > 40, "banner missing from the recorded frame"
    middle = slice(45, 75)
    assert np.abs(raw[middle] - labelled[middle]).mean() < np.abs(raw[:8] - labelled[:8]).mean()


def test_demo_bad_input_is_one_line_and_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert demo.main(["--code", "2,9", "--out", str(tmp_path)]) == 2
    assert demo.main(["--audio", str(tmp_path / "missing.wav"), "--out", str(tmp_path)]) == 2
    (tmp_path / "notes.md").write_text("2,3")
    assert demo.main(["--image", str(tmp_path / "notes.md"), "--out", str(tmp_path)]) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 3 and all(line.startswith("vafn-demo: error: ") for line in errors), errors
    assert "2,9" in errors[0] and "no such file" in errors[1] and ".png" in errors[2]


def test_expand_inputs_keeps_command_line_order_and_reads_folders(tmp_path: Path) -> None:
    from PIL import Image

    args = demo.build_parser().parse_args(["--code", "1", "--inputs", str(tmp_path), "--code", "3,2"])
    Image.new("L", (64, 32)).save(tmp_path / "b.png")
    (tmp_path / "a.txt").write_text("2,3\n")
    (tmp_path / "ignored.md").write_text("x")
    inputs = demo.expand_inputs(args.inputs)
    assert [(i.kind, i.label) for i in inputs] == [("code", "1"), ("code", "a.txt"), ("image", "b.png"),
                                                    ("code", "3,2")]
    assert inputs[1].value == "2,3"


class _Slow:
    """Delegates to the real generator after a delay longer than the whole step budget takes to simulate."""

    def __init__(self, generator: Any, delay_s: float) -> None:
        self.generator = generator
        self.delay_s = delay_s

    def transcribe(self, **kwargs: Any) -> Any:
        import time

        time.sleep(self.delay_s)
        return self.generator.transcribe(**kwargs)


def test_demo_waits_for_a_slow_reader_instead_of_spending_its_steps(tmp_path: Path) -> None:
    from vafn_media import InstructionGenerator

    generator = _Slow(InstructionGenerator.load(warm=False), delay_s=1.5)
    inputs = demo.expand_inputs([("code", "2")])
    result = demo.run_demo(inputs, tmp_path, generator=generator, interval=0, max_steps=60, video="none",
                           progress=False)
    assert [o.status for o in result.outcomes] == ["completed"], result.outcomes
