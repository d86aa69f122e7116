from cvvc.cli import main

raise SystemExit(main())
