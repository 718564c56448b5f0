"""`python -m epc_offboard` is `epc-offboard`."""

import sys

from epc_offboard.cli import main

sys.exit(main())
