"""`python -m intercap.synth OUT [options]`: the same as `intercap synth`."""
from intercap.synth.generator import main

raise SystemExit(main())
