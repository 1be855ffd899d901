"""Runs: their lifecycle and write-behind store (`lifecycle`), the jobs and leases workers take
(`scheduler`, `dispatch`, the in-process `executor`), stored populations (`population`,
`crud`) and TensorBoard files (`tracking`); docs/architecture.md."""
