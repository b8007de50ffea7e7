"""Regenerate the README's demo transcript by running the demo (a transcript is never typed).

``python -m implantplan.analyses.readme_transcript [--readme README.md]`` runs ``implantplan
demo`` exactly as the README's first command does (in a temporary folder, so nothing is left in
the checkout), and replaces the text between the ``<!-- demo-transcript:begin -->`` and
``<!-- demo-transcript:end -->`` markers of the README with what it printed (stdout and stderr in
order), the temporary folder shown as ``~``. ``normalized`` is what tests compare: the lines
without their timings, which change from run to run.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from implantplan.systems.errors import InputError
from implantplan.systems.files import write_text_atomic

BEGIN, END = "<!-- demo-transcript:begin -->", "<!-- demo-transcript:end -->"
_README = Path(__file__).resolve().parents[1] / "README.md"
_TIMING = [
    (re.compile(r"^\[\s*[\d.]+ s\] "), "[t] "),  # the progress prefix
    (re.compile(r"\b\d+(\.\d+)? s\b"), "<t> s"),  # durations
    (re.compile(r"realtime x[\d.]+"), "realtime x<r>"),
    (re.compile(r"^(plan|report): \S*/"), r"\1: <dir>/"),  # where the demo was run
]
_THROTTLED = re.compile(r"^\[t\] [^:]+: \d+/\d+ (generations|blocks)\b")  # shown about 2 per s


def run_demo() -> str:
    """The demo's output, as a user sees it in a fresh folder."""
    exe = Path(sys.executable).with_name("implantplan")
    with tempfile.TemporaryDirectory(prefix="implantplan-readme-") as tmp:
        done = subprocess.run([str(exe), "demo"], cwd=tmp, capture_output=False, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, check=False)
        text = done.stdout.replace(str(Path(tmp).resolve()), "~").replace(tmp, "~")
    if done.returncode != 0:
        raise InputError("demo", f"exited {done.returncode}:\n{text}")
    return text


def normalized(text: str) -> list[str]:
    """The transcript's lines without timings (and without the throttled progress lines)."""
    out = []
    for line in text.strip().splitlines():
        for pattern, repl in _TIMING:
            line = pattern.sub(repl, line)
        if not _THROTTLED.match(line):
            out.append(line)
    return out


def transcript_in(readme: str) -> str:
    """The transcript block of a README's text."""
    if BEGIN not in readme or END not in readme:
        raise InputError("README", f"no {BEGIN} ... {END} block")
    block = readme.split(BEGIN, 1)[1].split(END, 1)[0]
    return block.strip().removeprefix("```").removesuffix("```").strip()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m implantplan.analyses.readme_transcript",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--readme", type=Path, default=_README, help="README to update")
    args = ap.parse_args(argv)
    text = args.readme.read_text(encoding="utf-8")
    transcript_in(text)  # the markers must be there
    out = run_demo().strip()
    head, rest = text.split(BEGIN, 1)
    tail = rest.split(END, 1)[1]
    write_text_atomic(args.readme, f"{head}{BEGIN}\n```\n{out}\n```\n{END}{tail}")
    print(f"{args.readme}: transcript updated ({len(out.splitlines())} lines)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
