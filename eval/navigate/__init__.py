"""The navigation benchmark: every method at every sample budget on the BARN, forest, clutter and gap suites.

Three parts: :mod:`eval.navigate.records` (the records: keys, store, statistics, score; no torch), the runner
(``run``, ``episode``, ``execute``, ``robot_files``) and the reports (``results``, ``budget``, ``compare``,
``failures``, ``replay``, ``figures``, ``score``), which read records only through the records' public names.
``python -m eval.navigate [run] FLAGS`` runs it; the tools are subcommands (:mod:`eval.navigate.commands`).
"""

from eval.navigate.subcommands import refuse_old_spelling

refuse_old_spelling()  # python -m eval.navigate.compare ...: one line naming python -m eval.navigate compare
