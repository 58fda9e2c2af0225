"""`python -m eval`: see `eval.main`."""

import sys

from eval.main import main

if __name__ == "__main__":
  sys.exit(main())
