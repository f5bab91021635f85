"""``python -m hgsloc_plugin.cli``: the ``hgsloc`` command."""

import sys

from .parser import main

sys.exit(main())
