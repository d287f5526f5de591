"""What turns trainings into evidence: the run folder as the analysis tools read it
(:mod:`odmv.study.records`), the held-out set (:mod:`odmv.study.heldout`), and the analysis
verbs behind one command, ``python -m odmv.study <verb> ...`` (``--help`` lists them)."""

#: verb -> module of odmv.study; each module's docstring says what it does, its main(argv) does it
VERBS = {
    "summarize": "summarize",
    "heldout": "heldout",
    "robustness": "robustness",
    "heights": "heights",
    "shadows": "shadows",
    "split": "split",
    "rescore": "rescore",
    "ocd": "ocd",
    "coverage": "coverage",
    "symmetry": "symmetry",
    "phase": "phase",
    "captures": "captures",
    "graphs": "graphs",
    "prior": "prior",
    "uncertainty": "uncertainty",
}
