"""``python -m uimm_jax`` runs the command line."""

from uimm_jax.cli import main

raise SystemExit(main())
