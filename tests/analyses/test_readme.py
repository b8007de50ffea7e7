"""The README tells the truth: its demo transcript is what the demo prints today (made by
``python -m implantplan.analyses.readme_transcript``), its commands write under out/."""

from __future__ import annotations

import re
from pathlib import Path

from implantplan.analyses.readme_transcript import normalized, transcript_in

README = Path(__file__).resolve().parents[2] / "README.md"


def test_the_readme_transcript_is_what_the_demo_prints(demo_run):
    _, printed = demo_run
    readme = transcript_in(README.read_text(encoding="utf-8"))
    assert normalized(readme) == normalized(printed), (
        "README transcript is stale: run python -m implantplan.analyses.readme_transcript")


def test_readme_commands_write_under_out():
    text = README.read_text(encoding="utf-8")
    blocks = re.findall(r"```bash\n(.*?)```", text, flags=re.S)
    outs = [m for b in blocks for m in re.findall(r"--(?:out|png|html|plots)\s+(\S+)", b)]
    assert outs, "no output paths found in the README's commands"
    assert [o for o in outs if not o.startswith("out/")] == []
