"""The one stage runner and the summary a run prints when it ends."""
