"""The session store: the coordinator's durable state in ``session.db``, written as the run
goes (:mod:`.writer`, in the layout of :mod:`.schema`, its arrays packed by :mod:`.blobs`),
read back (:mod:`.reader`), the coordinator's memory bounded by paging out to it
(:mod:`.paging`), and a run continued from it (:mod:`.resume`). It knows nothing of the
runtimes above it (manual: docs/architecture.md, "Layers")."""
