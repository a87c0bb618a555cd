"""`python -m htlm_agent.cli ...` runs the `htlm` command line (what launch_scripts/team.sh calls)."""

import sys

from htlm_agent.cli import main

sys.exit(main())
