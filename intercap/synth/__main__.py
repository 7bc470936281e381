"""`python -m intercap.synth OUT [options]`: the same as `intercap synth`."""
from intercap.synth.options import build_arg_parser, config_from_args

args = build_arg_parser().parse_args()  # --help and usage errors answer before the generator's imports

from intercap.synth.generator import generate_session  # noqa: E402

generate_session(config_from_args(args), args.out)
raise SystemExit(0)
