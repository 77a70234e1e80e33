"""Time integration: the time loop (fixed and adaptive steps, differentiable), step-size control, schedules, frames and solutions."""
