"""``python -m tandemscan.daemon.cli``: the ``tandemscan`` command (:func:`tandemscan.daemon.cli.main`)."""

import sys

from tandemscan.daemon.cli import main

sys.exit(main())
