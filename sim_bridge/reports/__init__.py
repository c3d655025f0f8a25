"""What a run records and reports: the recorder (MissionTracker), typed results and
metrics, figures, summaries, and the launch studies. Imports the world and the scenario,
never the SITL or a harness."""
