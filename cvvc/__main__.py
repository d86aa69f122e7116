"""``python -m cvvc``: the ``cvvc`` command."""

from cvvc.cli import main

raise SystemExit(main())
