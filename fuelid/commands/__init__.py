"""One module per `fuelid` subcommand: HELP, add_arguments(parser), run(args) -> int."""
