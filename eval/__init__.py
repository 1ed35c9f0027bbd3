
from precompute.startup import install_when_run_as_command

install_when_run_as_command()  # python -m ...: Ctrl-C during the imports is one line and exit 130
