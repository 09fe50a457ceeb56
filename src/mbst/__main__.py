import sys

from mbst.cli import main

sys.exit(main())
