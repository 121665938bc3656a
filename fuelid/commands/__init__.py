"""One module per `fuelid` subcommand (its one-line help in fuelid.cli.COMMANDS): add_arguments(parser),
run(args) -> int."""
