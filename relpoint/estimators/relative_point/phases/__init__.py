"""The phases of one Relative Point iteration and of the end of the log, one module each, over the
state they share (:class:`~relpoint.estimators.relative_point.state.EstimatorState`)."""
