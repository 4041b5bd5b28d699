"""The papers hil implements, reproduced by one command each (``hil paper NAME``).

One module per paper (:mod:`hil.paper.energy`...), each with a function
``reproduce(options: PaperOptions) -> PaperReport``: it runs the paper's experiments in lockstep
on the emulators, redraws its figures into ``options.figures`` and returns its tables, figures
and findings, the paper's value beside hil's in every cell. :mod:`hil.paper.report` holds what
the papers share: the "paper | hil | ratio" tables, the report (Markdown, HTML, JSON) and the
check that every table and figure of the paper is in it. The command line's table of papers is
:data:`hil.cli.paper.PAPERS`.
"""
