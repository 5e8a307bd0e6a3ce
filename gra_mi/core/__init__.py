"""What every stage shares and no stage owns: errors, the runtime (Mitsuba variant, plugins, torch device), file I/O
with atomic writes, progress bars, metrics, reports and plots, and the training loop. Imports neither Mitsuba nor
torch at package import time."""
