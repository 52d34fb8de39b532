from benchmarks.accuracy.run import main

main()
