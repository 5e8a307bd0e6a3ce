"""gra-mi: Generative Relightable Avatars on Mitsuba 3 / Dr.Jit.

Importing this package loads neither Mitsuba nor torch and sets no Mitsuba variant: commands choose one with
:func:`gra_mi.render.runtime.start_runtime`.
"""

__version__ = "0.1.0"
