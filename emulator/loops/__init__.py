"""What steps an emulated vehicle besides its own `step`: the real-time loop (`realtime_runner`) and the
batched compiled steps of the lockstep runner's fast path (`batched_steps`)."""
