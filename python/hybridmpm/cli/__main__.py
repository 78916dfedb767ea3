"""``python -m hybridmpm.cli``: the ``hybridmpm`` command."""

import sys

from hybridmpm.cli import main

sys.exit(main())
