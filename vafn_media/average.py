"""Average the weights of fine-tuned checkpoints (a "model soup"): one reader that costs what one checkpoint costs.

The checkpoints must be fine-tunes of one modality's path from the same initial checkpoint (``python -m
vafn_media.train --init X --train-only audio``, different data seeds): their frozen weights are then identical and
only that modality's encoder and adapter differ, so those are averaged (BatchNorm statistics included) and everything
else is kept. The result is calibrated on the validation split of the first checkpoint's training arguments, as the
training command calibrates its own::

    python -m vafn_media.average runs/a/instruction_model.pt runs/b/instruction_model.pt --out runs/soup
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from vafn_media.constants import MODALITIES


#: Metadata that describes one training run, kept per checkpoint under "averaged" rather than as the average's own.
_RUN_RECORD: tuple[str, ...] = ("command", "init", "validation", "data_seconds", "total_seconds", "cpu_seconds")


def _averaged(name: str, modality: str) -> bool:
    """Whether weight ``name`` belongs to ``modality``'s encoder or adapter (what ``--train-only`` trains)."""
    return name.startswith((f"encoders.{modality}.", f"adapters.{modality}."))


def average_state_dicts(states: Sequence[dict], modality: str, weights: Sequence[float] | None = None) -> dict:
    """The weighted mean of ``modality``'s encoder and adapter over ``states``; every other tensor from the first.

    Raises ``ValueError`` when the checkpoints hold different tensors or shapes, or differ outside that modality's
    path (they are then not fine-tunes of that path from one initial checkpoint, and their average means nothing).

    :param states: two or more state dicts of the same model.
    :param modality: ``"audio"`` or ``"image"``.
    :param weights: one positive weight per state dict (normalised to sum to 1); default equal weights.
    """
    import torch

    if modality not in MODALITIES:
        raise ValueError(f"modality must be one of {MODALITIES}, got {modality!r}")
    if len(states) < 2:
        raise ValueError(f"averaging needs at least two checkpoints, got {len(states)}")
    weights = [1.0] * len(states) if weights is None else [float(w) for w in weights]
    if len(weights) != len(states) or not all(w > 0 for w in weights):
        raise ValueError(f"need one positive weight per checkpoint ({len(states)}), got {weights}")
    weights = [w / sum(weights) for w in weights]
    first = states[0]
    for index, state in enumerate(states[1:], start=1):
        if state.keys() != first.keys():
            raise ValueError(f"checkpoint {index} holds other tensors than checkpoint 0: not the same model")
        for name, tensor in first.items():
            if state[name].shape != tensor.shape:
                raise ValueError(f"checkpoint {index}: {name} has shape {tuple(state[name].shape)}, "
                                 f"checkpoint 0 {tuple(tensor.shape)}")
            if not _averaged(name, modality) and not torch.equal(state[name], tensor):
                raise ValueError(f"checkpoint {index} differs from checkpoint 0 in {name}, outside the {modality} "
                                 f"path: average only fine-tunes of that path from one initial checkpoint")
    averaged = {}
    for name, tensor in first.items():
        if _averaged(name, modality) and tensor.is_floating_point():
            averaged[name] = sum(w * state[name].double() for w, state in zip(weights, states)).to(tensor.dtype)
        else:  # frozen weights, and integer counters such as BatchNorm's num_batches_tracked
            averaged[name] = tensor.clone()
    return averaged


def main(argv: Sequence[str] | None = None) -> dict:
    """Command line: average checkpoints, write ``<out>/instruction_model.{pt,json}``, calibrate it."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", type=Path, nargs="+", help=".pt files, each with its .json beside it")
    parser.add_argument("--out", type=Path, required=True, help="folder for instruction_model.{pt,json}")
    parser.add_argument("--modality", choices=MODALITIES, default="audio", help="the path the checkpoints fine-tuned")
    parser.add_argument("--weights", type=float, nargs="+", default=None, help="one per checkpoint (default equal)")
    parser.add_argument("--cache-dir", type=Path, default=None, help="data cache for the calibration split")
    args = parser.parse_args(argv)
    for path in args.checkpoints:
        if not path.is_file() or not path.with_suffix(".json").is_file():
            parser.error(f"{path}: need the .pt file and its .json metadata beside it")
    import torch  # after the argument checks, so --help and a wrong path answer at once

    from vafn_gym.files import atomic_write
    from vafn_media.calibration import main as calibrate
    from vafn_media.train import CHECKPOINT_NAME

    try:
        state = average_state_dicts([torch.load(p, map_location="cpu", weights_only=True) for p in args.checkpoints],
                                    args.modality, args.weights)
    except ValueError as error:
        parser.error(str(error))
    ingredients = [json.loads(path.with_suffix(".json").read_text()) for path in args.checkpoints]
    # The first checkpoint's config and training arguments (its validation split calibrates the average); each
    # checkpoint's own record of its run goes under "averaged".
    metadata = {key: value for key, value in ingredients[0].items() if key not in _RUN_RECORD}
    metadata.update({
        "command": "python -m vafn_media.average " + " ".join(argv if argv is not None else sys.argv[1:]),
        "averaged": [{"checkpoint": str(path), **{key: meta[key] for key in _RUN_RECORD if key in meta}}
                     for path, meta in zip(args.checkpoints, ingredients)],
    })
    args.out.mkdir(parents=True, exist_ok=True)
    out = args.out / f"{CHECKPOINT_NAME}.pt"
    atomic_write(out, lambda tmp: torch.save(state, tmp))
    atomic_write(out.with_suffix(".json"), lambda tmp: tmp.write_text(json.dumps(metadata, indent=2)))
    calibrate(["--checkpoint", str(out)] + (["--cache-dir", str(args.cache_dir)] if args.cache_dir else []))
    return json.loads(out.with_suffix(".json").read_text())


if __name__ == "__main__":
    main()
