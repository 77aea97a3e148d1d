"""Reports of runs (``uabs-report``): the tables, the paper's claims and the figures
of a sweep, with the learned policies beside the baselines on the test traces."""
