"""``--help`` of the benchmark CLIs: it runs, names every option's default, and shows no raw reStructuredText markup.

Run in-process (``runpy`` with ``--help``), so it costs the imports only once per worker.
"""

from __future__ import annotations

import re
import runpy
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
WITH_DEFAULTS = [
    "baselines", "env_throughput", "instruction_table", "maml_step_cost", "scripted_ceiling",
    "learning", "adaptation", "adaptation_direction", "transfer", "export_pretrained", "failures", "speech_invariance",
]


def help_text(name: str, monkeypatch, capsys) -> str:
    path = ROOT / "benchmarks" / f"{name}.py"
    monkeypatch.setattr(sys, "argv", [str(path), "--help"])
    monkeypatch.syspath_prepend(str(path.parent))
    with pytest.raises(SystemExit) as exit_info:
        runpy.run_path(str(path), run_name="__main__")
    assert exit_info.value.code in (0, None)
    return capsys.readouterr().out


def option_blocks(text: str) -> dict[str, str]:
    """Option name -> its help text, from argparse's "options:" section."""
    section = text.split("\noptions:\n", 1)[1]
    blocks: dict[str, str] = {}
    current = None
    for line in section.splitlines():
        match = re.match(r"  (-[-\w]+)", line)
        if match:
            current = match.group(1)
            blocks[current] = line
        elif current:
            blocks[current] += " " + line.strip()
    return blocks


@pytest.mark.parametrize("name", WITH_DEFAULTS)
def test_benchmark_help_runs_without_markup(name, monkeypatch, capsys):
    text = help_text(name, monkeypatch, capsys)
    assert "usage:" in text
    assert "``" not in text


@pytest.mark.parametrize("name", WITH_DEFAULTS)
def test_benchmark_help_names_each_default(name, monkeypatch, capsys):
    blocks = option_blocks(help_text(name, monkeypatch, capsys))
    missing = [option for option, block in blocks.items() if option != "-h" and "default" not in block]
    assert not missing, f"{name}.py --help: no default shown for {missing}"


def test_sac_sanity_is_gone():
    """Issue 14 reported ``benchmarks/sac_sanity.py --help`` crashing; the script no longer exists."""
    assert not (ROOT / "benchmarks" / "sac_sanity.py").exists()
