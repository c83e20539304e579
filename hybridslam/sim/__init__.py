"""Simulators that write scenario files: the paper's Sec. V setup and the thesis's hallway."""
