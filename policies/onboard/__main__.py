"""`python -m policies.onboard`: run the onboard program (see `policies.onboard.cli`)."""

import os
import sys

from policies.onboard.cli import main

code = main()
# the program has closed its links and its event log: leave without the interpreter's teardown of the
# numerical libraries (~50-100 ms), which a harness in lockstep would otherwise wait out tick by tick
sys.stdout.flush()
sys.stderr.flush()
os._exit(code)
