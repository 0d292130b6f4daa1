"""The session use-cases (`SessionService`) and the pure changes they make (`app.sessions.changes`)."""

from app.sessions.batch import ObservationBatch
from app.sessions.service import Applied, GridRequest, NewSession, PreparedUtterance, SessionService
from app.sessions.summaries import Belief

__all__ = [
    "Applied",
    "Belief",
    "GridRequest",
    "NewSession",
    "ObservationBatch",
    "PreparedUtterance",
    "SessionService",
]
