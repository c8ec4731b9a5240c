"""Risk-aware route planning on velocity tubes (OMPL); built in a later issue."""
