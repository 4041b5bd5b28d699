"""The energy paper, reproduced: Diaz C. and Ocampo-Martinez, "Energy efficiency improvement of
machine tools via peripheral devices management: an optimization-based control approach".

:func:`reproduce` runs its experiments in lockstep on the emulated bench under its conditions
(``hil/configs/paper_energy.toml``) and returns the report: every table of the paper with its
values beside hil's, its figures redrawn from hil's sessions, and the J1 sensitivity study.
"""

from __future__ import annotations

from hil.bench.config import BenchConfig, load_bench_config
from hil.paper.energy_runs import paper_config
from hil.paper.report import PaperOptions, PaperReport, Section, Table

TITLE = ("Energy efficiency improvement of machine tools via peripheral devices management: "
         "reproduced by hil")
SOURCE = ("J. L. Diaz C. and C. Ocampo-Martinez, \"Energy efficiency improvement of machine tools "
          "via peripheral devices management: an optimization-based control approach\"")

#: the paper's tables and figures (and the figures of its text), each a part of the report
EXPECTED = ("Figs. 1-2", "Table I", "Fits (V-A)", "Fig. 3a", "Fig. 3b", "Fig. 3c", "Table II",
            "Peaks (V-D)", "Fig. 4a", "Fig. 4b", "Fig. 4c", "Table III", "Fig. 5", "Table IV",
            "Fig. 6", "J1 sensitivity")

#: Table I: alpha_j, eta_j [ud/s], the range [q_min, q_max] and q_j(0) of each resource
TABLE_I = {"q1": (-3.0, 5.0, 50.0, 150.0, 55.0), "q2": (-5.0, 7.0, 60.0, 180.0, 65.0)}


def reproduce(options: PaperOptions) -> PaperReport:
    """Run the paper's experiments and return its report."""
    config = load_bench_config(str(paper_config()))
    sections = [Section("The paper's conditions", (conditions_table(config),))]
    return PaperReport("energy", TITLE, SOURCE, EXPECTED, sections, {}, options.quick)


def conditions_table(config: BenchConfig) -> Table:
    """Table I as the paper gives it and as hil's runs use it."""
    rows = []
    for resource in config.plant.resources:
        alpha, eta, low, high, q0 = TABLE_I[resource.name]
        paper = f"{alpha:g} / {eta:g}, [{low:g}, {high:g}], {q0:g}"
        used = (f"{resource.alpha:g} / {resource.eta:g}, [{resource.bounds[0]:g}, "
                f"{resource.bounds[1]:g}], {resource.q0:g}")
        rows.append((f"{resource.supplier} ({resource.name})", paper, used,
                     "same" if paper == used else "DIFFERS"))
    return Table("Table I", "alpha_j / eta_j [ud/s], range [q_min, q_max], q_j(0)",
                 ("j", "paper", "hil", ""), tuple(rows))
