"""`python -m policies.onboard`: run the onboard program (see `policies.onboard.cli`)."""

from policies.onboard.cli import main_and_leave

main_and_leave()
