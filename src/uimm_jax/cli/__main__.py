"""``python -m uimm_jax.cli`` runs the command line."""

from uimm_jax.cli import main

raise SystemExit(main())
