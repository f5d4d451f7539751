"""Compare result files of ``faults_unknown_size.py`` cell by cell (session 13).

Usage: ``python compare.py BASE.json NEW.json``.  Since session 14 this runs
``../session14_retract/compare.py``, the same comparison with the retraction columns added
(its docstring says what each column is), so the comparison is written once.
"""

import pathlib
import runpy

if __name__ == "__main__":
    here = pathlib.Path(__file__).resolve().parent
    runpy.run_path(str(here.parent / "session14_retract" / "compare.py"), run_name="__main__")
