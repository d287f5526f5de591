"""Result pages: one self-contained, offline HTML file per run, report or prediction folder
(``python -m odmv.view PATH``). :mod:`.sources` reads a folder into a :class:`.sources.Page`,
:mod:`.plots` turns its scenes and tables into plotly figures, :mod:`.document` writes the HTML
with plotly.js inlined once."""
