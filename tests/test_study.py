"""python -m odmv.study: one command for the analysis verbs, each with its own --help."""

import pytest

from odmv.study import VERBS
from odmv.study.__main__ import main


def test_help_lists_every_verb_with_what_it_does(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for verb in VERBS:
        line = next(line for line in out.splitlines() if line.strip().startswith(verb + " "))
        assert len(line.split(maxsplit=1)[1]) > 20  # its docstring's first paragraph
    assert main([]) == 2  # no verb: the usage, and a failing status


@pytest.mark.parametrize("verb", sorted(VERBS))
def test_each_verb_tells_its_arguments(verb, capsys):
    with pytest.raises(SystemExit) as done:
        main([verb, "--help"])
    assert done.value.code == 0
    assert f"usage: python -m odmv.study {verb}" in capsys.readouterr().out


def test_an_unknown_verb_is_one_line_naming_the_verbs(capsys):
    assert main(["nope"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: 'nope' is no verb of odmv.study") and "summarize" in err
