"""Control design and analysis: actuation, linearisation, controllers."""
