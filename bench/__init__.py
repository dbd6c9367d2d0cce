"""torchfmap's benchmarks: one runner (``python -m bench SUITE``, ``bench/__main__.py``), its
cases by suite (``accuracy.py``, ``speed.py``, ``speed_match.py``, ``speed_torch.py``,
``learned.py``), the shared pair loader (``pairs.py``) and results writer (``common.py``), and
their settings (``configs/<suite>.json``). Results go to ``bench/results/<suite>_<case>.md``."""
