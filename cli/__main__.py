from mapkit.cli.main import main

main()
