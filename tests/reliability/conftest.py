from tests.reliability.helpers import no_board_contact, private_tmp

__all__ = ["no_board_contact", "private_tmp"]
