"""`python -m policies.onboard`: run the onboard program (see `policies.onboard.cli`)."""

import sys

from policies.onboard.cli import main

sys.exit(main())
