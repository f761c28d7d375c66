"""``python -m jaxrefl.cli``: the same as the ``jaxrefl`` command."""

import sys

from ._main import main

sys.exit(main())
