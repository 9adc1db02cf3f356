"""Bad and unusual input to the media reader: an error or a flag, never a confident wrong command; the CLI's contract.

Uses the packaged checkpoint. Speech comes from espeak-ng (held-out voices) and, when the ``flite`` program is
installed, from flite (an engine never used for training).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("librosa")
cv2 = pytest.importorskip("cv2")
soundfile = pytest.importorskip("soundfile")
pytest.importorskip("espeakng_loader")

torch.set_num_threads(1)

#: Spoken instructions of the cut-file tests (several lengths, so cuts fall mid-word and between words).
CUT_ARMS: tuple[tuple[int, ...], ...] = ((2, 3, 1, 3), (1, 2), (3, 3, 3), (2, 1, 3, 2, 1, 3), (1,), (3, 1, 2, 2, 1))
SILENCE_S = 0.3


@pytest.fixture(scope="module")
def generator():
    from vafn_media import InstructionGenerator

    return InstructionGenerator.load()


def _espeak(arms, voice: str = "en-us-nyc", variant: str = "m3") -> tuple[np.ndarray, int]:
    """A held-out espeak voice saying ``arms``, with the silences a recording has around it."""
    from vafn_media.speech import ESPEAK_SAMPLE_RATE, Voice, speak

    wave = speak(arms, Voice(voice, variant))
    pad = np.zeros(int(SILENCE_S * ESPEAK_SAMPLE_RATE), np.float32)
    return np.concatenate([pad, wave, pad]), ESPEAK_SAMPLE_RATE


def _outcome(generator, **kwargs) -> str:
    """"error", "flagged", "right" or "WRONG" (confident and wrong) for a transcription whose truth is ``arms``."""
    arms = kwargs.pop("arms")
    try:
        result = generator.transcribe(**kwargs)
    except ValueError:
        return "error"
    if result.low_confidence:
        return "flagged"
    return "right" if result.arms == tuple(arms) else "WRONG"


# --- audio -------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fraction", [0.5, 0.75])
def test_truncated_wav_files_are_errors(generator, tmp_path, fraction):
    """``head -c`` of a good WAV: the header promises more than the file holds -> ValueError naming the truncation."""
    for k, arms in enumerate(CUT_ARMS):
        wave, rate = _espeak(arms)
        good = tmp_path / f"good{k}.wav"
        soundfile.write(good, wave, rate, subtype="PCM_16")
        assert generator.transcribe(audio=str(good)).arms == arms
        cut = tmp_path / f"cut{k}.wav"
        data = good.read_bytes()
        cut.write_bytes(data[: int(len(data) * fraction)])
        with pytest.raises(ValueError, match="truncated"):
            generator.transcribe(audio=str(cut))


@pytest.mark.parametrize("fraction", [0.5, 0.75])
def test_cut_recordings_with_valid_headers_are_never_confidently_wrong_mid_word(generator, tmp_path, fraction):
    """A clip cut and saved again (valid header): when the cut falls inside a word the result is flagged or an
    error; a cut that falls in a pause is a complete shorter command and cannot be told apart (counted, not hidden)."""
    from vafn_media.audio import speech_problems
    from vafn_media.augment import resample

    outcomes = []
    for arms in CUT_ARMS:
        wave, rate = _espeak(arms)
        speech_end = len(wave) - int(SILENCE_S * rate)
        cut = wave[: int(speech_end * fraction)]
        path = tmp_path / "cut.wav"
        soundfile.write(path, cut, rate, subtype="PCM_16")
        outcome = _outcome(generator, audio=str(path), arms=arms)
        ends_loud = bool(speech_problems(resample(cut, rate, 16_000)))
        outcomes.append((outcome, ends_loud))
        if ends_loud:  # the cut fell inside a sound
            assert outcome in ("error", "flagged"), (arms, fraction, outcome)
    assert any(loud for _, loud in outcomes), "no cut fell mid-word: the test does not test anything"


def test_one_sample_and_tiny_files_are_errors(generator, tmp_path):
    for count in (1, 2, 100):
        path = tmp_path / f"tiny{count}.wav"
        soundfile.write(path, np.full(count, 0.3, np.float32), 16_000)
        with pytest.raises(ValueError, match="too short|empty"):
            generator.transcribe(audio=str(path))


def test_random_payload_audio_is_an_error(generator, tmp_path):
    rng = np.random.default_rng(0)
    for k, rate in enumerate((8_000, 16_000, 44_100)):
        path = tmp_path / f"random{k}.wav"
        soundfile.write(path, np.zeros(rate, np.int16), rate, subtype="PCM_16")
        data = bytearray(path.read_bytes())
        data[44:] = rng.integers(0, 256, len(data) - 44, dtype=np.uint8).tobytes()  # keep the header, random payload
        path.write_bytes(bytes(data))
        with pytest.raises(ValueError, match="noise"):
            generator.transcribe(audio=str(path))


def test_over_long_audio_is_rejected_from_the_header(generator, tmp_path):
    path = tmp_path / "long.wav"
    with soundfile.SoundFile(path, "w", 8_000, 1, "PCM_16") as handle:
        handle.write(np.zeros(8_000 * 25, np.int16))
    started = time.perf_counter()
    with pytest.raises(ValueError, match="from its header"):
        generator.transcribe(audio=str(path))
    assert time.perf_counter() - started < 1.0


@pytest.mark.parametrize("rate", [8_000, 11_025, 16_000, 96_000, 192_000])
def test_any_rate_from_8_to_192_khz_is_read(generator, rate):
    from vafn_media.augment import resample

    arms = (2, 3, 1, 3)
    wave, native = _espeak(arms)
    assert generator.transcribe(audio=(resample(wave, native, rate), rate)).arms == arms


def test_rates_outside_8_to_192_khz_are_errors(generator):
    wave = np.random.default_rng(0).normal(0, 0.1, 4000).astype(np.float32)
    for rate in (4_000, 384_000):
        with pytest.raises(ValueError, match="sample rate"):
            generator.transcribe(audio=(wave, rate))


# --- images ------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["uniform", "gaussian", "salt"])
def test_noise_images_are_errors(generator, kind):
    rng = np.random.default_rng(1)
    image = {"uniform": rng.integers(0, 256, (120, 400)).astype(np.uint8),
             "gaussian": np.clip(rng.normal(128, 40, (100, 300)), 0, 255).astype(np.uint8),
             "salt": ((rng.random((100, 300)) > 0.95) * 255).astype(np.uint8)}[kind]
    with pytest.raises(ValueError, match="noise"):
        generator.transcribe(image=image)


@pytest.mark.parametrize("shape", [(1, 2), (2, 1), (1, 1), (3, 300)])
def test_tiny_images_are_errors(generator, shape):
    image = np.random.default_rng(0).integers(0, 256, shape).astype(np.uint8)
    with pytest.raises(ValueError, match="too small"):
        generator.transcribe(image=image)


def test_pixel_limit_is_checked_before_decoding(generator, tmp_path):
    """A small PNG that decodes to 20,000 x 20,000 pixels is refused from its header, fast and without the memory."""
    import zlib

    def chunk(kind: bytes, payload: bytes) -> bytes:
        import struct

        return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))

    import struct

    side = 20_000
    rows = zlib.compress(b"".join(b"\x00" + bytes(side) for _ in range(64)), 9)  # a valid start; never decoded
    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0))
           + chunk(b"IDAT", rows) + chunk(b"IEND", b""))
    path = tmp_path / "huge.png"
    path.write_bytes(png)
    started = time.perf_counter()
    with pytest.raises(ValueError, match="pixels"):
        generator.transcribe(image=str(path))
    assert time.perf_counter() - started < 1.0
    with pytest.raises(ValueError, match="pixels"):
        generator.transcribe(image=np.zeros((9_000, 9_000), np.uint8))


# --- fusion ------------------------------------------------------------------------------------------------------
def test_disagreeing_modalities_are_flagged(generator):
    from vafn_media.strips import render_strip

    wave, rate = _espeak((2, 3, 1))
    image = render_strip([1, 1, 2, 2], np.random.default_rng(0), heldout=True)
    result = generator.transcribe(audio=(wave, rate), image=image)
    assert set(result.readings["audio"]) and result.readings["audio"] != result.readings["image"]
    assert result.low_confidence and any("disagree" in w for w in result.warnings)
    assert result.method == "rescored"


def _reading(path, scale=1.0):
    """Greedy reading of CTC logits that follow ``path`` (frame labels) with sharpness ``scale``."""
    from vafn_media.constants import LATENT_DIM, VOCAB_SIZE
    from vafn_media.decoding import greedy_decode

    logits = torch.full((len(path), VOCAB_SIZE), -4.0)
    logits[torch.arange(len(path)), torch.tensor(path)] = 4.0
    return greedy_decode(torch.zeros(len(path), LATENT_DIM), logits * scale)


def test_fusion_weighs_every_modalitys_evidence_and_calibrates():
    from vafn_media.decoding import calibrated, fuse, reading_confidence

    assert calibrated(0.9, (1.0, 0.0)) == pytest.approx(0.9)
    assert calibrated(0.95, (1.0, -3.8)) < 0.5 < calibrated(0.9, (1.0, 1.3))
    image = _reading([0, 2, 0, 3, 0, 1, 0, 0], scale=2.0)            # sharp: [2, 3, 1]
    audio = _reading([0, 2, 2, 0, 3, 3, 0, 0], scale=0.6)            # soft, drops the last token: [2, 3]
    assert image.arms == [2, 3, 1] and audio.arms == [2, 3]
    fused = fuse({"audio": audio, "image": image}, None)
    assert fused.arms == [2, 3, 1] and fused.method == "rescored"
    calibration = {"audio": (1.0, 0.0), "image": (1.0, -6.0)}      # validation says: this image is rarely right
    capped = fuse({"audio": audio, "image": image}, None, None, calibration)
    assert max(capped.confidences) <= calibrated(reading_confidence(image), calibration["image"])
    agree = fuse({"audio": _reading([0, 1, 0, 2]), "image": _reading([1, 0, 2, 0])}, None)
    assert agree.method == "agree" and agree.arms == [1, 2] and all(c > 0.99 for c in agree.confidences)


def test_reading_confidence_is_the_weakest_token_not_a_noisy_pause():
    from vafn_media.constants import BLANK, LATENT_DIM, VOCAB_SIZE
    from vafn_media.decoding import greedy_decode, reading_confidence

    sharp = _reading([0, 2, 0, 0, 3, 0])
    logits = sharp.log_probs.clone()
    logits[2, :] = -4.0
    logits[2, BLANK], logits[2, 1] = 0.2, 0.0                      # a pause the model is unsure about
    paused = greedy_decode(torch.zeros(6, LATENT_DIM), logits)
    assert paused.arms == [2, 3] and paused.weakest < 0.6
    assert reading_confidence(paused) == pytest.approx(min(paused.confidences)) and reading_confidence(paused) > 0.99
    weak = _reading([0, 2, 0, 3, 0], scale=0.3)                    # uncertain tokens lower it
    assert reading_confidence(weak) == pytest.approx(min(weak.confidences)) and reading_confidence(weak) < 0.9
    all_blank = torch.zeros(3, VOCAB_SIZE).index_fill_(1, torch.tensor([BLANK]), 1.0)
    empty = greedy_decode(torch.zeros(3, LATENT_DIM), all_blank)
    assert empty.arms == [] and reading_confidence(empty) == pytest.approx(empty.weakest)


def test_low_confidence_threshold_is_a_load_option(generator):
    from vafn_gym.queue import InstructionQueue
    from vafn_media import InstructionGenerator, MultimediaStream
    from vafn_media.constants import LOW_CONFIDENCE

    wave, rate = _espeak((2, 3, 1))
    result = generator.transcribe(audio=(wave, rate))
    assert generator.low_confidence == LOW_CONFIDENCE and result.arms == (2, 3, 1) and not result.low_confidence
    assert LOW_CONFIDENCE <= result.confidence < 1.0
    strict = InstructionGenerator.load(warm=False, low_confidence=1.0)
    assert strict.transcribe(audio=(wave, rate)).low_confidence
    assert MultimediaStream(InstructionQueue(), strict).min_confidence == 1.0         # the stream follows its generator
    assert MultimediaStream(InstructionQueue(), strict, min_confidence=0.0).min_confidence == 0.0


def test_fusion_calibration_never_lets_fusion_lose_to_the_better_modality():
    from vafn_media.calibration import CalibrationSet, calibrate_fusion

    right_soft, right_sharp = _reading([0, 2, 0, 3, 0, 1, 0, 0], 0.5), _reading([0, 2, 0, 3, 0, 1, 0, 0], 1.0)
    wrong_soft, wrong_sharp = _reading([0, 2, 2, 0, 3, 3, 0, 0], 0.5), _reading([0, 2, 2, 0, 3, 3, 0, 0], 1.0)
    label = [(2, 3, 1)]
    unseen_voice = CalibrationSet("audio confidently wrong", [wrong_sharp], [right_soft], label)
    cutout = CalibrationSet("image wrong", [right_sharp], [wrong_soft], label)
    grid = (0.6, 1.0, 2.0, 3.0)
    both = calibrate_fusion([unseen_voice, cutout], grid)
    assert both["fusion_weights"] == {"audio": 1.0, "image": 2.0}        # the only weight right on both sets
    assert both["calibration"]["worst_margin_by_image_weight"] == {"0.6": -1.0, "1.0": -1.0, "2.0": 0.0, "3.0": -1.0}
    assert calibrate_fusion([cutout], grid)["fusion_weights"]["image"] == 1.0   # ties: the more even weighting
    assert calibrate_fusion([unseen_voice], (0.6, 1.0))["calibration"]["worst_margin_by_image_weight"]["1.0"] < 0


def test_masked_readings_do_not_flatten_the_confidence_calibration():
    import dataclasses

    from vafn_media.calibration import CalibrationSet, calibrate_fusion
    from vafn_media.decoding import calibrated, reading_confidence

    right, label = _reading([0, 2, 0, 3, 0, 1, 0, 0], 0.6), (2, 3, 1)
    wrong, soft_wrong = _reading([0, 2, 0, 3, 0, 3, 0, 0], 0.6), _reading([0, 2, 0, 3, 0, 3, 0, 0], 0.3)
    guesses = [dataclasses.replace(wrong, masked=(4, 6))] * 30  # a hidden digit guessed as confidently as a seen one
    seen = [right] * 30 + [soft_wrong] * 10
    clean = CalibrationSet("clean", [right] * 40, seen, [label] * 40)
    cutout = CalibrationSet("Cutout", [right] * 30, guesses, [label] * 30)
    platt = calibrate_fusion([clean, cutout], (1.0,))["confidence_calibration"]["image"]
    assert calibrated(reading_confidence(right), platt) > 0.9  # fitted on the seen readings only
    assert calibrated(reading_confidence(soft_wrong), platt) < 0.5


def test_unseen_positions_are_what_a_masked_reading_left_out():
    from vafn_media.decoding import unseen_positions

    assert unseen_positions([2, 3, 1, 3], [2, 1, 3]) == [1]
    assert unseen_positions([1, 1, 2], [1, 2]) == [1]  # leftmost match: the second 1 is the hidden one
    assert unseen_positions([2, 3], [2, 3]) == [] and unseen_positions([2, 3], [3, 2]) is None


def test_a_masked_image_confirms_what_it_saw_and_the_audio_alone_vouches_for_the_rest(generator):
    import dataclasses

    audio = _reading([0, 2, 0, 3, 0, 1, 0, 0])  # every token ~0.999
    image = dataclasses.replace(_reading([0, 2, 0, 0, 0, 1, 0, 0]), masked=(3, 5))  # the 3 was under the mask
    weak_seen = dataclasses.replace(audio, confidences=[0.5, *audio.confidences[1:]])
    weak_hidden = dataclasses.replace(audio, confidences=[audio.confidences[0], 0.5, audio.confidences[2]])
    # the weak 2 was seen by the image too: only the hidden 3 rests on the audio alone
    assert generator.hidden_token_confidence({"audio": weak_seen, "image": image}, [2, 3, 1]) > 0.9
    assert generator.hidden_token_confidence({"audio": weak_hidden, "image": image}, [2, 3, 1]) < 0.5
    # the mask hid no token: a word both readings missed must not look certain, so the token-wise rule does not apply
    nothing_hidden = dataclasses.replace(_reading([0, 2, 0, 3, 0, 1, 0, 0]), masked=(6, 7))
    assert generator.hidden_token_confidence({"audio": weak_seen, "image": nothing_hidden}, [2, 3, 1]) is None
    assert generator.hidden_token_confidence({"audio": weak_seen, "image": image}, [2, 1, 3]) is None  # not its reading


def test_condition_calibration_sets_read_training_voices_under_every_condition(generator):
    from vafn_media.augment import CONDITIONS
    from vafn_media.calibration import condition_sets

    sets = condition_sets(generator, count=2, seed=3)
    assert [s.name for s in sets] == [f"training voices, {c}" for c in CONDITIONS] + [
        "training voices, Table 1 noise + Cutout"]
    assert all(len(s.audio) == len(s.image) == len(s.labels) == 2 for s in sets)
    assert all(0.0 <= s.accuracy(m) <= 1.0 for s in sets for m in ("audio", "image"))


# --- the stream ----------------------------------------------------------------------------------------------------
def test_stream_never_enqueues_bad_or_cut_input(generator, tmp_path):
    from vafn_gym.queue import InstructionQueue
    from vafn_media import MultimediaStream

    wave, rate = _espeak((2, 3, 1, 3))
    good = tmp_path / "good.wav"
    soundfile.write(good, wave, rate, subtype="PCM_16")
    truncated = tmp_path / "truncated.wav"
    truncated.write_bytes(good.read_bytes()[: len(good.read_bytes()) // 2])
    speech_end = len(wave) - int(SILENCE_S * rate)
    queue = InstructionQueue()
    with MultimediaStream(queue, generator) as stream:
        stream.submit(audio=str(good))
        stream.submit(audio=str(truncated))
        stream.submit(audio=np.full(1, 0.5, np.float32), sample_rate=16_000)
        stream.submit(image=np.random.default_rng(0).integers(0, 256, (120, 400)).astype(np.uint8))
        stream.submit(image=np.zeros((1, 2), np.uint8))
        stream.submit(audio=(wave[: int(0.62 * speech_end)], rate))
        assert stream.wait(60)
    statuses = [event.status for event in sorted(stream.events, key=lambda e: e.ticket)]
    assert statuses[0] == "enqueued" and len(queue) == 1, [(e.status, e.message) for e in stream.events]
    assert all(status in ("error", "rejected") for status in statuses[1:]), statuses


# --- CLI -----------------------------------------------------------------------------------------------------------
def _cli(*args: str) -> subprocess.CompletedProcess:
    code = ("import sys\nfrom vafn_media.cli import main\ntry:\n    rc = main(sys.argv[1:])\nexcept SystemExit as e:\n"
            "    rc = e.code\nprint('TORCH' if 'torch' in sys.modules else 'NOTORCH', file=sys.stderr)\nsys.exit(rc)")
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=120)


def _error_lines(done: subprocess.CompletedProcess) -> list[str]:
    """Every stderr line but the test's own torch marker (so a stray banner or warning counts too)."""
    return [line for line in done.stderr.splitlines() if line not in ("TORCH", "NOTORCH")]


def test_cli_help_and_path_errors_do_not_import_torch(tmp_path):
    done = _cli("--help")
    assert done.returncode == 0 and "--audio" in done.stdout and "NOTORCH" in done.stderr
    for args in (("--audio", str(tmp_path / "missing.wav")), ("--image", str(tmp_path)),
                 ("--code", "1", "--checkpoint", str(tmp_path / "none.pt")), ("--bogus",), ()):
        done = _cli(*args)
        assert done.returncode == 2, (args, done.stderr)
        assert len(_error_lines(done)) == 1 and "NOTORCH" in done.stderr, (args, done.stderr)


def test_cli_bad_inputs_exit_2_with_one_line(tmp_path):
    from vafn_media.generator import DEFAULT_CHECKPOINT

    bad_ckpt = tmp_path / "model.pt"
    bad_ckpt.write_bytes(DEFAULT_CHECKPOINT.read_bytes()[:5000])
    (tmp_path / "model.json").write_text(DEFAULT_CHECKPOINT.with_suffix(".json").read_text())
    tiny = tmp_path / "tiny.wav"
    soundfile.write(tiny, np.full(1, 0.3, np.float32), 16_000)
    garbage = tmp_path / "garbage.png"
    garbage.write_bytes(b"not an image" * 20)
    for args in (("--code", "1", "--checkpoint", str(bad_ckpt)), ("--audio", str(tiny)), ("--image", str(garbage)),
                 ("--code", "[4, 1]"), ("--code", "two")):
        done = _cli(*args)
        assert done.returncode == 2, (args, done.stdout, done.stderr)
        assert len(_error_lines(done)) == 1, (args, done.stderr)
    assert "corrupt" in _error_lines(_cli("--code", "1", "--checkpoint", str(bad_ckpt)))[0]


def test_reading_an_instruction_never_loads_the_simulator():
    code = ("import sys\nfrom vafn_media.cli import main\nrc = main(['--code', '2,3'])\n"
            "print('PYBULLET' if 'pybullet' in sys.modules else 'NOPYBULLET')\nsys.exit(rc)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.splitlines()[-1] == "NOPYBULLET", (done.stdout, done.stderr)
    assert done.stderr == "", done.stderr  # no simulator banner among the CLI's output


def test_cli_empty_code_is_the_empty_instruction():
    done = _cli("--code", "", "--json")
    assert done.returncode == 0, done.stderr
    assert '"instruction": []' in done.stdout


def test_camera_checkpoint_comparison(load_benchmark, tmp_path):
    from vafn_media.camera import CAMERA_CONDITIONS
    from vafn_media.evaluation import CAMERA_SETS

    module = load_benchmark("camera_checkpoints")
    out = tmp_path / "cards.md"
    module.main(["--items", "2", "--out", str(out)])
    lines = out.read_text().splitlines()
    rows = [line for line in lines if line.startswith("| ") and not line.startswith("| Glyphs")]
    assert len(rows) == len(CAMERA_SETS) * len(CAMERA_CONDITIONS) and all(row.count("|") == 4 for row in rows)
    assert lines[-1].startswith("- packaged: unseen sets") and lines[-1].endswith("vs the first column +0.0")
    first = {("unseen a", "flat"): 100.0, ("unseen a", "all"): 90.0, ("training b", "all"): 50.0}
    second = {("unseen a", "flat"): 97.0, ("unseen a", "all"): 95.0, ("training b", "all"): 0.0}
    lines = module.summary({"one": first, "two": second})
    assert lines[1] == ('- two: unseen sets, mean of every cell 96.00, of the "all" cells 95.00; largest drop of an '
                        "unseen cell vs the first column -3.0")  # the training set's drop does not count


def test_speech_checkpoint_comparison_and_error_breakdown(generator, load_benchmark):
    from types import SimpleNamespace

    from vafn_media.evaluation import speech_items

    module = load_benchmark("speech_checkpoints")
    items = speech_items("espeak", 3, module.SELECTION_SEED)
    assert all(item.voice and 0 <= item.template for item in items)
    lines = module.error_lines(generator.transcribe, items, "espeak")
    assert [line.split(":")[0] for line in lines] == ["- espeak, clean, per phrasing (shown for [1, 2])",
                                                      "- espeak, clean, per voice", "- espeak, clean, digits dropped"]

    def deaf(audio):  # reads every clip as the empty instruction: every digit is dropped, every item wrong
        return SimpleNamespace(instruction=SimpleNamespace(arms=()))

    dropped = module.error_lines(deaf, items, "espeak")
    assert " 0 % of" in dropped[1] and "100 %" not in dropped[1]
    counts = {arm: sum(item.arms.count(arm) for item in items) for arm in (1, 2, 3)}
    assert f"dropped: { {arm: n for arm, n in counts.items() if n} }, inserted: {{}}" in dropped[2]
