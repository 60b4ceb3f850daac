"""Before the flight: the flight plan and its ground control, and the check of a plan or a flight against GCPs."""
