"""``python -m odmv.study <verb> [args]``: the analysis verbs; ``--help`` lists them and
``python -m odmv.study <verb> --help`` tells one's arguments."""

from __future__ import annotations

import importlib
import sys

from odmv.cli import run_app
from odmv.study import VERBS


def _summary(verb: str) -> str:
    """The first paragraph of the verb's module docstring, on one line."""
    doc = importlib.import_module(f"odmv.study.{VERBS[verb]}").__doc__ or ""
    return " ".join(doc.strip().split("\n\n")[0].split())


def usage() -> str:
    width = max(map(len, VERBS))
    lines = [f"  {verb:<{width}}  {_summary(verb)}" for verb in VERBS]
    return "usage: python -m odmv.study <verb> [args] (<verb> --help for its own)\n\nverbs:\n" + (
        "\n".join(lines)
    )


def main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0 if argv else 2
    verb, rest = argv[0], argv[1:]
    if verb not in VERBS:
        print(
            f"error: {verb!r} is no verb of odmv.study; choose {', '.join(VERBS)}", file=sys.stderr
        )
        return 2
    sys.argv[0] = f"python -m odmv.study {verb}"  # argparse's usage line names the verb
    module = importlib.import_module(f"odmv.study.{VERBS[verb]}")
    return run_app(lambda: module.main(rest)) or 0  # its faults in one line, as every app


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
