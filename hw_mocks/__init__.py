"""The simulated bench: membrane physics, rendering, objects, and twins of the arm, camera and pressure board."""
