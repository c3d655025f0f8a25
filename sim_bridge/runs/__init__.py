"""The harnesses: the headless runner (`simulate`), the Monte Carlo sweep, the 40-process
fleet (`run`), the fuzzer, and run directories. The top layer: nothing below imports it."""
