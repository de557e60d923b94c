"""``python -m robotd`` is the ``robotd`` command."""

from __future__ import annotations

import sys

from robotd.tools.cli import main

sys.exit(main())
