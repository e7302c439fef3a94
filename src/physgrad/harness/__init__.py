"""The harness: everything that speaks names and strings — the registry of methods and
problems, configurations and their digests, the command line, studies, statistics, figures
and the bench — built on the core library (update rules, routes, the engine), which never
imports it."""
