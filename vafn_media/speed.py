"""Thread-CPU time of ``InstructionGenerator.transcribe`` per call, optionally against an earlier commit, interleaved.

Items are the held-out split's items of Table 1's first seed (``generate_raw(1000, "heldout", n, difficulty)``), read
as the Table-1 rows "Audio" and "Audio-Visual" (features included, corruption excluded, as in
:func:`vafn_media.evaluation.run_cell`). With ``--before REV`` the ``vafn_media`` package of git revision REV is
extracted into a temporary directory under another name and loaded beside the current one; the two readers then
alternate item by item (which one goes first alternates too), so both see the same machine load, and every result is
compared: same arm ids, flags, method and warnings, confidences within 1e-5.

    OMP_NUM_THREADS=1 python -m vafn_media.speed --items 200 --before 390ec71
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIDENCE_TOLERANCE = 1e-5


def load_before(rev: str, directory: str):
    """The InstructionGenerator class of ``vafn_media`` at git revision ``rev``, imported as ``vafn_media_before``."""
    import importlib
    import io

    archive = subprocess.run(["git", "archive", rev, "vafn_media"], cwd=ROOT, check=True, capture_output=True).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(directory, filter="data")
    package = Path(directory) / "vafn_media_before"
    (Path(directory) / "vafn_media").rename(package)
    for path in package.rglob("*.py"):
        path.write_text(path.read_text().replace("vafn_media", "vafn_media_before"))
    sys.path.insert(0, directory)
    return importlib.import_module("vafn_media_before.generator").InstructionGenerator


def same(a, b) -> bool:
    """Whether two transcribe outcomes (a Transcription or a ValueError message) agree."""
    if isinstance(a, str) or isinstance(b, str):
        return a == b
    if (a.arms, a.low_confidence, a.method, a.warnings, a.readings) != (b.arms, b.low_confidence, b.method,
                                                                         b.warnings, b.readings):
        return False
    return len(a.confidences) == len(b.confidences) and max(
        [abs(a.confidence - b.confidence)] + [abs(x - y) for x, y in zip(a.confidences, b.confidences)]
    ) <= CONFIDENCE_TOLERANCE


def main(argv=None) -> None:
    """Time each row and difficulty; print the table, the ratio to ``--before`` and the identity check."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--items", type=int, default=200, help="items per difficulty")
    parser.add_argument("--rows", default="Audio,Audio-Visual", help="Table-1 rows, comma-separated")
    parser.add_argument("--before", default=None, help="git revision to compare with (interleaved)")
    args = parser.parse_args(argv)
    import torch

    from vafn_gym.constants import DIFFICULTY_LENGTHS
    from vafn_media.dataset import generate_raw
    from vafn_media.evaluation import corrupted_inputs
    from vafn_media.generator import InstructionGenerator

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as directory:
        readers = {"after": InstructionGenerator.load()}
        if args.before:
            readers = {"before": load_before(args.before, directory).load(), **readers}
        data = {d: generate_raw(1000, "heldout", args.items, d) for d in DIFFICULTY_LENGTHS}
        compared = mismatches = 0
        print(f"thread CPU per transcribe call (ms), mean over {args.items} held-out items; load average "
              f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
        for row in args.rows.split(","):
            for difficulty, items in data.items():
                times: dict = {name: [] for name in readers}
                for i in range(len(items.arms)):
                    kwargs = corrupted_inputs(items, 1000, i, row)
                    order = list(readers) if i % 2 == 0 else list(readers)[::-1]
                    results = {}
                    for name in order:
                        start = time.thread_time()
                        try:
                            results[name] = readers[name].transcribe(**kwargs)
                        except ValueError as error:
                            results[name] = str(error)
                        times[name].append(1000 * (time.thread_time() - start))
                    if len(results) == 2:
                        compared += 1
                        mismatches += not same(results["before"], results["after"])
                means = {name: float(np.mean(t)) for name, t in times.items()}
                text = "  ".join(f"{name} {value:.2f}" for name, value in means.items())
                if "before" in means:
                    text += f"  after/before {means['after'] / means['before']:.3f}"
                print(f"| {row} | {difficulty} | {text} |", flush=True)
        if args.before:
            print(f"identity: {compared} results compared, {mismatches} differ (arm ids, flags, method, warnings; "
                  f"confidences within {CONFIDENCE_TOLERANCE:g})")


if __name__ == "__main__":
    main()
