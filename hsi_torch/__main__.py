"""``python -m hsi_torch`` is the ``hsi-torch`` command."""

from hsi_torch.cli import main

raise SystemExit(main())
