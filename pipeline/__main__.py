"""``python -m ede_pipeline`` is ``ede-pipeline``."""

from ede_pipeline.cli import main

main()
