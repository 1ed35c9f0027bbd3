"""The navigation benchmark: every method at every sample budget on the BARN, forest, clutter and gap suites; records, statistics, comparisons, failures, replays."""
