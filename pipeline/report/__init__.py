"""Stage 5, ``ede-pipeline report``: one self-contained HTML page of every result.

The package's parts: :mod:`.command` is the click command and writes the page's files.
"""
