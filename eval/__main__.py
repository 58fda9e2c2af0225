"""`python -m eval`: see `eval.main`."""

import sys

try:
  from eval.main import main
except KeyboardInterrupt:  # Ctrl-C while the program loads: one line, not a traceback
  print("eval: interrupted", file=sys.stderr)
  sys.exit(130)

if __name__ == "__main__":
  sys.exit(main())
