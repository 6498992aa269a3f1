"""How the processes of a run reach each other: typed, versioned messages (:mod:`.messages`,
encoded without pickle by :mod:`.codec`), the transport interface (:mod:`.links`) and what
carries it: pipes on one machine (:mod:`.pipes`) and Zenoh across machines (:mod:`.zenoh_hub`,
:mod:`.zenoh_agent`, an agent's :mod:`.spool`), a team's certificates and access rules
(:mod:`.team`, :mod:`.team_access`). It knows nothing of the session store or the runtimes
above it (manual: docs/architecture.md, "Layers")."""
