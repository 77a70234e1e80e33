"""``python -m jaxvisco.cli``: the ``jaxvisco`` command."""

import sys

from ._main import main

sys.exit(main())
