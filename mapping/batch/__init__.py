"""Many sequences at once (``radiomap batch``): one task per sequence on Ray or on local processes, each writing
``OUT/<name>/`` exactly as the single command does, resumable, with a summary across sequences.

One job per module:

- :mod:`~mapping.batch.commands`: the work of ``radiomap reconstruct`` and ``radiomap compare`` on one sequence as
  library functions of the command's options (the commands call them; so does each task), and :data:`COMMANDS`,
  one entry per command a batch runs;
- :mod:`~mapping.batch.worker`: one task in a worker process (thread limits, its log, a plain result);
- :mod:`~mapping.batch.runner`: :func:`run_batch`, the tasks on Ray or local processes (skip complete folders,
  rerun the others, progress);
- :mod:`~mapping.batch.sequences`: the sequence list and the results folders' names (kept across resumes);
- :mod:`~mapping.batch.resume`: what a resumed batch checks in OUT (the run that made a folder, changed options,
  damaged folders);
- :mod:`~mapping.batch.report`: ``OUT/summary.csv`` and ``OUT/index.html``.
"""

from mapping.batch.commands import COMMANDS, BatchCommand, MethodChoiceError
from mapping.batch.report import summary_rows, write_summary
from mapping.batch.runner import ENGINES, BatchError, Outcome, Task, cpu_count, ray_available, run_batch
from mapping.batch.sequences import folder_names, read_sequence_list, task_names
from mapping.batch.worker import THREAD_VARIABLES, thread_environment

__all__ = ["BatchCommand", "BatchError", "COMMANDS", "ENGINES", "MethodChoiceError", "Outcome", "THREAD_VARIABLES",
           "Task", "cpu_count", "folder_names", "ray_available", "read_sequence_list", "run_batch", "summary_rows",
           "task_names", "thread_environment", "write_summary"]
