from drivelab.cli import main

main()
