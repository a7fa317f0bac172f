"""Code the tests share: plain functions and constants, imported as
`tests.helpers.<module>` (fixtures live in tests/conftest.py).

- paths: the repository and the scenes shared beside it (../shared);
- cli: the `dosppm` command run as a child process, free loopback ports;
- scenes: built-in scenes at a small resolution;
- chunks: scenes chunked in memory without the subdivider;
- cluster: the single-process SPPM reference and the comparison within
  noise that the cluster tests share;
- netns: hosts as Linux network namespaces (the multi-host tests).
"""
