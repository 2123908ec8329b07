"""softcrawl: co-design of pneumatic soft crawling robots and their gaits.

Pipeline packages: :mod:`softcrawl.geometry` -> :mod:`softcrawl.fem` -> (reduction) ->
:mod:`softcrawl.robot` -> (environment) -> (co-design) -> (hardware).
Units throughout: mm, kg, s; force mN; pressure and stress kPa.
"""

__version__ = "0.4.0"
