from oodrl.cli import main

main()
