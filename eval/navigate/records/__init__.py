"""The navigation benchmark's records: what a run writes and every report reads. No torch, nothing of the runner.

* :mod:`~eval.navigate.records.keys`: the key a record is stored under (:func:`episode_key`);
* :mod:`~eval.navigate.records.store`: a benchmark folder, ``settings.json`` + ``episodes.jsonl``, its one parser
  (:class:`EpisodeStore`; :func:`load_folder`, :func:`load_episode` for a reader);
* :mod:`~eval.navigate.records.cycle_hist`: per-command wall times as mergeable histograms;
* :mod:`~eval.navigate.records.stats`: summaries with Wilson intervals, paired comparisons against the best
  baseline (:func:`best_baseline`, :func:`by_episode`, :func:`compare_pair`, :func:`paired_comparisons`);
* :mod:`~eval.navigate.records.score`: the BARN Challenge's score of an episode (:func:`barn_score`).

The runner (``eval.navigate.episode``, ``.execute``, ``.run``) writes records through these; the reports
(``python -m eval.navigate budget|compare|failures|replay|figures``) read them only through the public names here.
``tests/test_nav_records.py`` checks that importing this package leaves torch unloaded.
"""

from eval.navigate.records.cycle_hist import cycle_histogram, histogram_quantile, merge_histograms
from eval.navigate.records.keys import episode_key
from eval.navigate.records.score import barn_score, score_summary
from eval.navigate.records.stats import (
    best_baseline,
    by_episode,
    compare_pair,
    fmt_rate,
    fmt_score,
    mcnemar_exact_p,
    newcombe_paired_interval,
    paired_comparisons,
    summarize,
)
from eval.navigate.records.store import (
    OUTCOMES,
    EpisodeStore,
    StoreError,
    check_record,
    check_settings,
    load_episode,
    load_folder,
)

__all__ = ["episode_key", "EpisodeStore", "StoreError", "load_folder", "load_episode", "OUTCOMES", "check_record", "check_settings",
           "cycle_histogram", "merge_histograms", "histogram_quantile", "summarize", "best_baseline", "by_episode",
           "compare_pair", "paired_comparisons", "newcombe_paired_interval", "mcnemar_exact_p", "fmt_rate",
           "fmt_score", "barn_score", "score_summary"]
