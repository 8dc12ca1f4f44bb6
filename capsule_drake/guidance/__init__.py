"""The pseudo-force on the operator's hand: its terms and its system."""
