"""``python -m benchmarks``: every benchmark (``make bench``)."""

from benchmarks.suite import main

raise SystemExit(main())
