"""The navigation worlds: BARN maps (shipped data, format, Gazebo conversion), the seeded forest, clutter and gap generators, their geometry, the benchmark's tasks and robot."""
