"""``python -m cpas_bayes``: the command line."""

import sys

from cpas_bayes.app.entry import main

sys.exit(main())
