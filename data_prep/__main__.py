"""``python -m data_prep``: the ``data_prep`` command (:mod:`data_prep.cli`)."""
import sys

from data_prep.cli import main

sys.exit(main())
