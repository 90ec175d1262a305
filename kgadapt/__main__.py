from kgadapt.cli import main

raise SystemExit(main())
