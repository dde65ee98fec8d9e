"""Scenario files (floor 4, the core's top): parsed, run, judged.

``scenario`` reads the YAML files, runs each (offline, or through the
supervisor) and gives the verdicts, the JUnit XML and the report.

May import: every floor of the core below it.
"""
