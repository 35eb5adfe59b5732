"""``python -m pemviz``: the ``pemviz`` program, as the console script runs it (:func:`pemviz.cli.main`)."""

import sys

from pemviz.cli import main

sys.exit(main())
