"""`python -m oodrl` and the `oodrl` command (its entry point is this module's `main`, so that a
checkout from before `oodrl.warm` put first on PYTHONPATH, as benchmarks do for a baseline,
runs its own CLI: importing its `__main__` did that)."""

from oodrl.warm import main

if __name__ == "__main__":
    main()
