"""The robot side of the server: the zenoh service of the robot agents (`service`), its parts
(`traces`, `replacement`, `pushes`, `registry`), their settings (`settings`) and tables
(`store`), the Colony page's map (`map`) and the signing of what is sent to them (`signing`);
docs/robots.md."""
