"""``python -m eval.bench_long`` (the command issue 42 names) runs ``eval.bench.long``."""

from eval.bench.long import main

if __name__ == "__main__":
    raise SystemExit(main())
