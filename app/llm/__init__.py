"""LLM clients: the hypothesis proposer and the foundation-model baseline grounders, over any
OpenAI-compatible chat-completions endpoint."""

from app.llm.baselines import LLMEndToEndGrounder, ScaffoldedLLMGrounder
from app.llm.client import ChatClient, EndpointUnavailable, LLMEndpoint
from app.llm.proposer import LLMProposer

__all__ = [
    "ChatClient",
    "EndpointUnavailable",
    "LLMEndToEndGrounder",
    "LLMEndpoint",
    "LLMProposer",
    "ScaffoldedLLMGrounder",
]
