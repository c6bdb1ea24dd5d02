"""``python -m personalize.cohort REQUEST.json``: one subject's job in a process of its own."""
import sys

from personalize.cohort.process import child_main

sys.exit(child_main(sys.argv[1]))
