import sys

from mrctl.cli import main

sys.exit(main())
