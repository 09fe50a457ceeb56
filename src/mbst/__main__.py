import sys

from mbst.cli import main

if __name__ == "__main__":  # a spawned process imports this module without running it
    sys.exit(main())
