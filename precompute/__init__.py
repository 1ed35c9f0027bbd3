"""Building C-Uniform tables: level sets, max-flow and coverage builders, table sets and map-table farms."""

from precompute.startup import install_when_run_as_command

install_when_run_as_command()  # python -m ...: Ctrl-C during the imports is one line and exit 130
