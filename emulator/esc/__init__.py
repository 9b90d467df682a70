"""The motors behind DroneCAN ESCs on a CAN bus: the bus model (`bus`), its compiled arithmetic
(`kernels`), its settings (`config`, loadable without the model) and the services every node answers
(`services`)."""
