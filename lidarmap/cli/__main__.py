from lidarmap.cli import main

main()
