"""The four commands (``uabs-traces``, ``uabs-train``, ``uabs-eval``, ``uabs-report``),
their console entry points and the Hydra plumbing they share: the top of the package,
which nothing else imports."""
