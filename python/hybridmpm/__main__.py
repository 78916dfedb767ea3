import sys

from hybridmpm.cli import main

sys.exit(main())
