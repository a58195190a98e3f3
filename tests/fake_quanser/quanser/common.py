"""Fake ``quanser.common``: GenericError and Timeout, as the real package names them."""


class GenericError(Exception):
    def __init__(self, error_code, detail=""):
        Exception.__init__(self, str(error_code))
        self.error_code = error_code
        self.detail = detail

    def get_error_message(self):
        from quanser import _fake

        text = _fake.MESSAGES.get(self.error_code, "error")
        return text + (": " + self.detail if self.detail else "")


class Timeout(object):
    def __init__(self, seconds=0, nanoseconds=0):
        self.seconds, self.nanoseconds = seconds, nanoseconds
