"""`python -m capsule_drake.app`: the `capsule-sim` command."""

import sys

from capsule_drake.app.entry import main

sys.exit(main())
