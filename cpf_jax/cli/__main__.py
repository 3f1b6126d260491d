"""``python -m cpf_jax.cli``: the same command as ``cpf-track``."""

import sys

from cpf_jax.cli import main

sys.exit(main())
