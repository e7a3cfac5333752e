from ._app.cli import main

raise SystemExit(main())
