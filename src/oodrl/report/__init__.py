"""The report of SPEC §7: markdown tables (`tables`), figures and DVC plot data (`plots`), and
the terminal view of a results file (`show`). Import the submodules; matplotlib is only
imported when a figure is drawn."""
