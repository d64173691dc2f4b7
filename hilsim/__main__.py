from hilsim.cli import main

raise SystemExit(main())
